"""Read and edit a Klipper ``printer.cfg`` the way Klipper reads it.

Klipper's rules (klippy/configfile.py, read 2026-11): the file's line endings are
normalised to LF; the block after the SAVE_CONFIG header (``AUTOSAVE_HEADER``) is split
off, its ``#*# `` prefixes stripped, and any option it shares with the regular part is
commented out (the regular part wins); in the regular part everything after a ``#`` is
dropped, a line that matches configparser's section pattern ``[header]`` starts a
section, and ``[include GLOB]`` is replaced by the files the glob matches (relative to the
including file, sorted), parsed in place; the whole is read by
``RawConfigParser(strict=False, inline_comment_prefixes=(';', '#'))`` chunk by chunk, so
a section or option seen again later overrides the earlier one.

So the value Klipper uses for ``[extruder] pressure_advance`` is the *last* assignment
in include order; that is the line to edit. Appending a section at the end of the file
puts it inside the SAVE_CONFIG block, which Klipper then rejects as a whole ("modifications
after header") and refuses to start.
"""
from __future__ import annotations

import configparser
import glob
import io
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from calib.errors import UserError

AUTOSAVE_HEADER = ("\n#*# <---------------------- SAVE_CONFIG ---------------------->\n"
                   "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n#*#\n")
SECTION_RE = configparser.RawConfigParser.SECTCRE
OPTION_RE = re.compile(r"(?P<option>[^:=\s][^:=]*?)\s*(?P<sep>[:=])\s*(?P<value>.*)$")


@dataclass
class Assignment:
    """Where an option is set: file, 0-based line index, section, option (lower case), value."""

    file: Path
    line: int
    section: str
    option: str
    value: str


@dataclass
class ConfigTree:
    """The regular part of printer.cfg and every file it includes, in Klipper's read order."""

    main: Path
    texts: dict = field(default_factory=dict)       # Path -> original text (line endings kept)
    headers: list = field(default_factory=list)     # (Path, line, section) in read order
    assignments: list = field(default_factory=list)  # Assignment, in read order
    autosave: str = ""                               # SAVE_CONFIG block, prefixes stripped

    def last(self, section: str, option: str) -> Assignment | None:
        hits = [a for a in self.assignments if a.section == section and a.option == option]
        return hits[-1] if hits else None


def read_exact(path) -> str:
    """The file's text with its line endings as they are (no newline translation)."""
    with open(path, encoding="utf-8", newline="") as f:
        return f.read()


def _lines(text: str) -> list[str]:
    return text.replace("\r\n", "\n").split("\n")


def _strip_comment(line: str) -> str:
    pos = line.find("#")
    line = line if pos < 0 else line[:pos]
    # configparser's inline ';' comments need whitespace before them
    m = re.search(r"(^|\s);", line)
    return line if m is None else line[:m.start()]


def read_tree(path, read=None) -> ConfigTree:
    """Walk printer.cfg and its includes. ``read(Path) -> str`` (default: the file on disk)
    lets an edit be checked before anything is written."""
    read = read or read_exact
    main = Path(path)
    tree = ConfigTree(main)

    def walk(p: Path, stack: tuple):
        key = Path(os.path.abspath(p))
        if key in stack:
            raise UserError(f"{p} includes itself (recursive [include])")
        try:
            text = read(p)
        except (OSError, UnicodeDecodeError) as exc:
            raise UserError(f"cannot read Klipper config {p}: {exc}") from None
        tree.texts[p] = text
        lines = _lines(text)
        if p == main:
            norm = "\n".join(lines)
            pos = norm.find(AUTOSAVE_HEADER)
            if pos >= 0:
                tree.autosave = "\n".join(ln[4:] for ln in norm[pos + len(AUTOSAVE_HEADER):].split("\n"))
                lines = norm[:pos].split("\n")
        section = None
        for i, raw in enumerate(lines):
            line = _strip_comment(raw)
            m = SECTION_RE.match(line)
            if m:
                header = m.group("header")
                if header.startswith("include "):
                    spec = os.path.join(os.path.dirname(p), header[8:].strip())
                    found = sorted(glob.glob(spec))
                    if not found and not glob.has_magic(spec):
                        raise UserError(f"{p}:{i + 1}: included file {spec} does not exist")
                    for inc in found:
                        walk(Path(inc), stack + (key,))
                    section = None
                else:
                    section = header
                    tree.headers.append((p, i, header))
                continue
            if not line.strip() or raw[:1].isspace() or section is None:
                continue
            mo = OPTION_RE.match(line)
            if mo:
                tree.assignments.append(Assignment(p, i, section, mo.group("option").strip().lower(),
                                                   mo.group("value").strip()))

    walk(main, ())
    return tree


def effective_value(path, section: str, option: str, read=None) -> str | None:
    """The value Klipper would read, by its own parser (configparser with Klipper's
    options) fed in Klipper's order, SAVE_CONFIG duplicates of regular options dropped."""
    tree = read_tree(path, read)
    cp = configparser.RawConfigParser(strict=False, inline_comment_prefixes=(";", "#"))

    def feed(p: Path):
        lines = _lines(tree.texts[p])
        if p == tree.main:
            norm = "\n".join(lines)
            pos = norm.find(AUTOSAVE_HEADER)
            lines = (norm[:pos] if pos >= 0 else norm).split("\n")
        buf = []
        for raw in lines:
            line = raw if raw.find("#") < 0 else raw[:raw.find("#")]
            m = SECTION_RE.match(line)
            if m and m.group("header").startswith("include "):
                cp.read_string("\n".join(buf), str(p))
                buf = []
                spec = os.path.join(os.path.dirname(p), m.group("header")[8:].strip())
                for inc in sorted(glob.glob(spec)):
                    feed(Path(inc))
            else:
                buf.append(line)
        cp.read_string("\n".join(buf), str(p))

    try:
        feed(tree.main)
        regular = {(s, o) for s in cp.sections() for o in cp.options(s)}
        if tree.autosave.strip():
            auto = configparser.RawConfigParser(strict=False, inline_comment_prefixes=(";", "#"))
            auto.read_string(tree.autosave)
            extra = io.StringIO()
            for s in auto.sections():
                extra.write(f"[{s}]\n")
                for o in auto.options(s):
                    if (s, o) not in regular:
                        extra.write(f"{o}: {auto.get(s, o)}\n")
            cp.read_string(extra.getvalue())
    except configparser.Error as exc:
        raise UserError(f"{path} is not a valid Klipper config: {str(exc).splitlines()[0]}") from None
    return cp.get(section, option) if cp.has_option(section, option) else None


def set_options(path, section: str, values: dict) -> dict:
    """:func:`set_option` for several options of one section; new texts {Path: text}."""
    new: dict = {}

    def read(p):
        return new[Path(p)] if Path(p) in new else read_exact(p)
    for option, value in values.items():
        new.update(set_option(path, section, option, value, read=read))
    return new


def set_option(path, section: str, option: str, value: str, read=None) -> dict:
    """New texts {Path: text} that make Klipper read ``option: value`` in ``[section]``
    (empty when it already does). Edits the last assignment Klipper reads (in an included
    file if that is where it is), else adds the option under the last ``[section]`` header;
    never touches the SAVE_CONFIG block. Line endings and comments are kept."""
    read = read or read_exact
    tree = read_tree(path, read)
    if not tree.headers:
        raise UserError(f"{path} has no [section] headers: not a Klipper printer.cfg")
    a = tree.last(section, option)
    if a is not None:
        target, idx = a.file, a.line
        raw = _lines(tree.texts[target])[idx]
        mo = OPTION_RE.match(_strip_comment(raw))
        comment = raw[len(_strip_comment(raw)):].strip()
        new_line = f"{raw[:mo.start('value')]}{value}" + (f"  {comment}" if comment else "")
        replace = True
    else:
        heads = [h for h in tree.headers if h[2] == section]
        if not heads:
            names = sorted({h[2] for h in tree.headers if h[2].startswith("extruder")})
            raise UserError(f"no [{section}] section in {path} or the files it includes"
                            + (f" (found: {', '.join(names)}; choose one with --section)" if names else
                               "; is this the printer's main printer.cfg?"))
        target, idx, _ = heads[-1]
        new_line, replace = f"{option}: {value}", False
    if effective_value(path, section, option, read=read) == value:
        return {}
    text = tree.texts[target]
    eol = "\r\n" if "\r\n" in text else "\n"
    lines = text.replace("\r\n", "\n").split("\n")
    if replace:
        lines[idx] = new_line
    else:
        lines.insert(idx + 1, new_line)
    new = {target: eol.join(lines)}
    got = effective_value(path, section, option,
                          read=lambda p: new[Path(p)] if Path(p) in new else read(p))
    if got != value:        # never write a file Klipper would read differently
        raise UserError(f"could not set [{section}] {option} in {path}: Klipper would read {got!r}")
    return new
