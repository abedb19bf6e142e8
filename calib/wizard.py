"""`calib wizard`: a guided session for someone who has a printer and a phone.

It asks one question at a time (printer, test, where to save), writes the pattern,
optionally streams it to the printer over USB serial, waits for the photo or scan (or
lets the virtual printer make one), measures, fits, says what is missing, and shows the
line to paste into the firmware. Each answer has a default in [brackets]; every step
runs the same `calib` verb a user could run by hand, and the wizard prints it.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from calib.demo import _Runner, _data_dir
from calib.errors import UserError

PATTERN_CHOICES = ("spiral-step", "stop-mid-path", "retract", "start-stop")


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


def run_wizard(inp=sys.stdin, out=sys.stdout, port: str | None = None, baud: int = 115200) -> dict:
    from patterns.profile import load_profile, shipped_profiles

    ask = Asker(inp, out)
    r = _Runner(Path("."), out)
    r.say("calib wizard: print a test, photograph it, get your extruder's constants.\n")
    names = sorted(shipped_profiles())
    printer = ask.ask(f"printer profile (one of {', '.join(names)}, or a path to your TOML)", names[0])
    profile = load_profile(printer)
    folder = Path(ask.ask("folder for the files", "calib-session"))
    folder.mkdir(parents=True, exist_ok=True)
    pattern = ask.ask(f"test pattern ({', '.join(PATTERN_CHOICES)})", recommend_pattern(profile),
                      PATTERN_CHOICES)
    gcode = folder / f"{pattern}.gcode"
    man = folder / f"{pattern}.manifest.json"
    r.step("writing the test pattern", ["pattern", pattern, "--printer", printer, "-o", gcode])
    r.step("preview", ["preview", gcode, "-o", folder / f"{pattern}.preview.png"])
    r.say(f"   open {folder / (pattern + '.preview.png')} to see what will be printed")

    send = bool(port) or ask.yes("send it to the printer over USB now?", False)
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
    else:
        r.say(f"   print {gcode} on your printer (single layer), let it cool.")

    r.say("\nPhotograph the print from above (all four square markers in view, no flash glare), "
          "or scan it on a flatbed at 600 dpi.")
    scan_answer = ask.ask("path to the photo or scan (or 'virtual' to let the virtual printer make one)",
                          "virtual")
    if scan_answer == "virtual":
        scan = folder / "scan.png"
        r.step("virtual print and scan", ["simulate", gcode, "--truth",
                                          _data_dir() / "truths" / "bowden.toml", "-o", scan])
    else:
        scan = Path(scan_answer).expanduser()
    widths = folder / "widths.csv"
    r.step("measuring", ["measure", scan, "--manifest", man, "-o", widths, "--overlay", folder / "qa.png"])
    r.say(f"   check {folder / 'qa.png'}: the green outline must sit on your printed lines")

    model = ask.ask("model to fit ('auto' adds the effects the scan supports)", "auto")
    fit_json = folder / "fit.json"
    r.step("fitting", ["fit", widths, "--manifest", man, "--model", model, "-o", fit_json], ok_codes=(0, 3))
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
                   ["fit", widths, "--manifest", man, "--model", model, "-o", fit_json], ok_codes=(0, 3))
    flavour = {"klipper": "klipper", "marlin": "marlin", "rrf": "rrf"}.get(profile.firmware, "marlin")
    from calib.commands.fit import verdict_text
    from fit.result import load_fit_json
    from fit.trust import assess

    verdict = assess(load_fit_json(fit_json))
    r.say(verdict_text(verdict.to_json()))
    if not verdict.trustworthy:
        r.say("   no firmware line: fix what is listed above first (the values would be wrong)")
        return {"folder": str(folder), "model": model, "fit": str(fit_json), "trustworthy": False}
    r.step(f"your firmware line ({flavour})", ["export", fit_json, "--to", flavour])
    return {"folder": str(folder), "model": model, "fit": str(fit_json)}
