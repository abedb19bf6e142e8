"""Every flag of every `calib` command is in the README's command reference (issue #10:
"README flag list complete"), so a new flag cannot ship undocumented."""
import argparse
from pathlib import Path

from calib.cli import build_parser

README = Path(__file__).resolve().parent.parent / "README.md"


def _reference() -> str:
    text = README.read_text()
    start = text.index("## Command reference")
    return text[start:text.index("\n## ", start + 1)]


def test_every_flag_of_every_command_is_in_the_readme_reference():
    ref = _reference()
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    missing = []
    for name, parser in sub.choices.items():
        block = ref[ref.index(f"**`calib {name}"):]
        end = block.find("\n**`calib ", 1)
        block = block if end < 0 else block[:end]
        missing += [f"calib {name} {o}" for a in parser._actions for o in a.option_strings
                    if o.startswith("--") and o != "--help" and f"`{o}`" not in block]
    assert not missing, "not in README's command reference: " + ", ".join(missing)
