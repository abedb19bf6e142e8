"""`calib wizard`: a guided session for someone who has a printer and a phone.

It asks one question at a time (printer, test, where to save), writes the pattern,
optionally streams it to the printer over USB serial, waits for the photo or scan (or
lets the virtual printer make one), measures, fits, says what is missing, and shows the
line to paste into the firmware. Each answer has a default in [brackets]; every step
runs the same `calib` verb a user could run by hand, and the wizard prints it.
"""
from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path

from calib.demo import _Runner, _data_dir
from calib.errors import UserError

PATTERN_CHOICES = ("spiral-step", "stop-mid-path", "retract", "start-stop", "probe")


class Asker:
    """Prompts on ``out``, reads answers from ``inp``; EOF on a pipe is a clear error."""

    def __init__(self, inp=sys.stdin, out=sys.stdout):
        self.inp, self.out = inp, out

    def ask(self, question: str, default: str = "", choices=None) -> str:
        while True:
            hint = f" [{default}]" if default else ""
            print(f"? {question}{hint}: ", end="", file=self.out, flush=True)
            line = self.inp.readline()
            if not line:
                raise UserError("the wizard ran out of answers (stdin closed); run it in a terminal "
                                "or pipe one answer per line")
            answer = line.strip() or default
            if choices and answer not in choices:
                print(f"  please answer one of: {', '.join(choices)}", file=self.out)
                continue
            return answer

    def yes(self, question: str, default: bool = False) -> bool:
        return self.ask(question + " (y/n)", "y" if default else "n", ("y", "n", "yes", "no")).startswith("y")


def recommend_pattern(profile) -> str:
    """Spiral step tests separate tau best (seed 004); a direct drive's short tau is also
    read well from stop-mid-path ooze (seed 000) but the spiral works for both."""
    return "spiral-step"


SESSION_FILE = "session.json"


class Session:
    """What a wizard session has done, kept in FOLDER/session.json so that a second run
    resumes: answers given and steps finished (a step whose output file is gone is redone)."""

    def __init__(self, folder: Path):
        self.path = folder / SESSION_FILE
        self.data = {"answers": {}, "done": []}
        if self.path.exists():
            try:
                self.data = json.loads(self.path.read_text())
            except (OSError, ValueError):
                pass      # a damaged session file: start afresh, the outputs are still there

    def answer(self, key: str):
        return self.data["answers"].get(key)

    def remember(self, key: str, value) -> None:
        self.data["answers"][key] = value
        self.save()

    def done(self, step: str, output: Path | None = None) -> bool:
        return step in self.data["done"] and (output is None or Path(output).exists())

    def finish(self, step: str) -> None:
        if step not in self.data["done"]:
            self.data["done"].append(step)
        self.save()

    def save(self) -> None:
        from calib.fileio import atomic_write_text

        atomic_write_text(self.path, json.dumps(self.data, indent=1))


def _virtual_truth(profile) -> Path:
    """The virtual printer's truth that matches the printer: a direct drive's tau is ~10x
    shorter than a Bowden's (data/truths)."""
    name = "direct_drive.toml" if profile.bowden_length_mm <= 0 else "bowden.toml"
    return _data_dir() / "truths" / name


def _ask_model(ask: Asker, r, profile, default: str) -> str:
    from fit.model import build_model

    while True:
        model = ask.ask("model to fit ('auto' adds the effects the scan supports)", default)
        if model == "auto":
            return model
        try:
            build_model(model, profile.to_dict())
            return model
        except UserError as exc:       # a typo must not end the session
            r.say(f"   {exc}")


def run_wizard(inp=sys.stdin, out=sys.stdout, port: str | None = None, baud: int = 115200) -> dict:
    from patterns.profile import load_profile, shipped_profiles

    ask = Asker(inp, out)
    r = _Runner(Path("."), out)
    r.say("calib wizard: print a test, photograph it, get your extruder's constants.\n")
    names = sorted(shipped_profiles())
    while True:
        printer = ask.ask(f"printer profile (one of {', '.join(names)}, or a path to your TOML)", names[0])
        try:
            profile = load_profile(printer)
            break
        except UserError as exc:       # a typo or a broken TOML must not end the session
            r.say(f"   {exc}")
    folder = Path(ask.ask("folder for the files", "calib-session"))
    folder.mkdir(parents=True, exist_ok=True)
    sess = Session(folder)
    if sess.data["done"]:
        if ask.yes(f"{folder} has a session ({', '.join(sess.data['done'])} done): resume it?", True):
            r.say("   resuming: finished steps are skipped")
        else:
            sess.data = {"answers": {}, "done": []}
    pattern = sess.answer("pattern") or ask.ask(f"test pattern ({', '.join(PATTERN_CHOICES)})",
                                                recommend_pattern(profile), PATTERN_CHOICES)
    sess.remember("pattern", pattern)
    gcode = folder / f"{pattern}.gcode"
    man = folder / f"{pattern}.manifest.json"
    if not sess.done("pattern", man):
        r.step("writing the test pattern", ["pattern", pattern, "--printer", printer, "-o", gcode])
        r.step("preview", ["preview", gcode, "-o", folder / f"{pattern}.preview.png"])
        sess.finish("pattern")
    r.say(f"   open {folder / (pattern + '.preview.png')} to see what will be printed")

    send = not sess.done("sent") and (bool(port) or ask.yes("send it to the printer over USB now?", False))
    if send and not ask.yes(f"open {folder / (pattern + '.preview.png')}: is that what you expect, "
                            "the bed clear and the nozzle clean? start printing now (it heats "
                            "and homes)?", False):
        r.say("   not sent: print it when the printer is ready, then come back with the photo")
        send = False
    if send:
        from calib.progress import progress as progress_bar
        from calib.sender import open_port, send_gcode

        dev = port or ask.ask("serial port", "/dev/ttyUSB0")
        with progress_bar(total=1, desc="sending", unit="line") as bar:
            def progress(done, total):
                bar.total = total
                bar.n = done
                bar.refresh()

            rep = send_gcode(open_port(dev, baud), gcode.read_text(), progress=progress)
        r.say(f"   sent {rep.lines_sent} lines ({rep.resends} resends) in {rep.seconds:.0f} s")
        sess.finish("sent")
    elif not sess.done("sent"):
        r.say(f"   print {gcode} on your printer (single layer), let it cool.")

    widths = folder / "widths.csv"
    while not sess.done("measure", widths):
        r.say("\nPhotograph the print from above (all four square markers in view, no flash glare), "
              "or scan it on a flatbed at 600 dpi. On a textured plate take 3-5 photos from the same "
              "place, the lamp moved around the print between them: its specks move, the bead does not.")
        scan_answer = ask.ask("path to the photo or scan, or several separated by spaces (or 'virtual' "
                              "to let the virtual printer make one)", "virtual")
        if scan_answer == "virtual":
            scans = [folder / "scan.png"]
            r.step("virtual print and scan", ["simulate", gcode, "--truth", _virtual_truth(profile),
                                              "-o", scans[0]])
        else:
            try:
                scans = [Path(a).expanduser() for a in shlex.split(scan_answer)]
            except ValueError as exc:     # an unclosed quote
                r.say(f"   {exc}; try again")
                continue
            bad = [str(a) for a in scans if not a.is_file()]
            if bad:
                r.say(f"   {', '.join(bad)} {'is not a file' if len(bad) == 1 else 'are not files'}; try again")
                continue
        try:
            r.step("measuring", ["measure", *scans, "--manifest", man, "-o", widths,
                                 "--overlay", folder / "qa.png"])
        except UserError as exc:          # a bad photo: say why and ask for another
            r.say(f"   {exc}")
            continue
        sess.remember("scan", " ".join(shlex.quote(str(a)) for a in scans))
        sess.finish("measure")
    r.say(f"   check {folder / 'qa.png'}: the green outline must sit on your printed lines")

    fit_json = folder / "fit.json"
    model = sess.answer("model")
    if not sess.done("fit", fit_json):
        model = _ask_model(ask, r, profile, "auto")
        r.step("fitting", ["fit", widths, "--manifest", man, "--model", model, "-o", fit_json],
               ok_codes=(0, 3))
        if model == "auto":
            model = json.loads(fit_json.read_text()).get("model", model)
        elif ask.yes("look for a missing physical effect (diagnose)?", True):
            diag = folder / "diagnose.json"
            r.step("diagnosing", ["diagnose", widths, "--manifest", man, "--model", model, "-o", diag])
            cands = json.loads(diag.read_text()).get("candidates", [])
            if cands and cands[0].get("delta_bic", 0) >= 10 and \
                    ask.yes(f"fit the extended model {model}+{cands[0]['effect']}?", True):
                model = f"{model}+{cands[0]['effect']}"
                r.step("fitting the extended model",
                       ["fit", widths, "--manifest", man, "--model", model, "-o", fit_json],
                       ok_codes=(0, 3))
        sess.remember("model", model)
        sess.finish("fit")
    from calib.commands.fit import verdict_text
    from fit.result import load_fit_json
    from fit.trust import assess

    verdict = assess(load_fit_json(fit_json))
    r.say(verdict_text(verdict.to_json()))
    if not verdict.trustworthy:
        r.say("   no firmware line: fix what is listed above first (the values would be wrong)")
        return {"folder": str(folder), "model": model, "fit": str(fit_json), "trustworthy": False}
    _exports(ask, r, profile, fit_json)
    return {"folder": str(folder), "model": model, "fit": str(fit_json), "trustworthy": True}


def _exports(ask: Asker, r, profile, fit_json: Path) -> None:
    """The exports the user picks; each printed, or written into a file they name."""
    from calib.commands.export import TARGETS

    flavour = {"klipper": "klipper", "marlin": "marlin", "rrf": "rrf"}.get(profile.firmware, "marlin")
    while True:
        picked = [t.strip() for t in ask.ask(f"exports, comma separated ({', '.join(TARGETS)}; "
                                             "'none' for none)", flavour).split(",") if t.strip()]
        bad = [t for t in picked if t not in TARGETS and t != "none"]
        if not bad:
            break
        r.say(f"   unknown export(s) {', '.join(bad)}; choose from {', '.join(TARGETS)}")
    for t in picked:
        if t == "none":
            continue
        target = "" if t == "spoolman" else ask.ask(     # Spoolman: printed, no file
            f"file to update for {t} (printer.cfg, preset, start G-code; blank: just print it)", "")
        argv = ["export", fit_json, "--to", t] + (["--profile", target] if target else [])
        try:
            r.step(f"export for {t}", argv)
        except UserError as exc:
            r.say(f"   {exc}")
