"""Generated documentation stays current: ``docs/cli.md`` is exactly what
``python -m clod_adapter.cli.reference`` writes, and it covers every installed command."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from clod_adapter.cli.reference import cli_reference

REPO = Path(__file__).resolve().parents[1]
CLI_DOC = REPO / "docs" / "cli.md"
REGENERATE = "python -m clod_adapter.cli.reference > docs/cli.md"


def project_scripts() -> list[str]:
    """The command names of pyproject.toml's [project.scripts] (a regex: no tomllib on 3.10)."""
    text = (REPO / "pyproject.toml").read_text()
    m = re.search(r"^\[project\.scripts\][ \t]*\n(.*?)(?=^\[|\Z)", text, re.M | re.S)
    assert m, "pyproject.toml has no [project.scripts] table"
    return re.findall(r"^\s*\"?([A-Za-z0-9_.-]+)\"?\s*=", m.group(1), re.M)


def test_cli_reference_is_current():
    expected = cli_reference()
    actual = CLI_DOC.read_text(encoding="utf-8") if CLI_DOC.is_file() else None
    assert actual == expected, (f"{CLI_DOC.relative_to(REPO)} is out of date with the CLIs' argparse parsers; "
                                f"regenerate it in the repository root with: {REGENERATE}")


def test_cli_reference_has_a_section_per_command():
    scripts = project_scripts()
    assert len(scripts) >= 5, scripts
    sections = re.findall(r"^## (\S+)$", cli_reference(), re.M)
    assert sorted(sections) == sorted(scripts), \
        "docs/cli.md's sections must be pyproject.toml's [project.scripts] (update _COMMANDS in clod_adapter/cli/reference.py)"
    assert set(re.findall(r"^## (\S+)$", CLI_DOC.read_text(encoding="utf-8"), re.M)) >= set(scripts), \
        f"docs/cli.md lacks a command; regenerate it with: {REGENERATE}"


def test_cli_reference_is_deterministic_and_plain():
    text = cli_reference()
    assert text == cli_reference()
    assert text.endswith("\n") and not text.endswith("\n\n\n")
    assert "%(" not in text and "%%" not in text  # argparse's help expansion applied
    assert not any(line.startswith(("| `-h`", "| `--help`")) for line in text.splitlines())
    for line in text.splitlines():
        if line.startswith("| "):
            assert line.endswith(" |") and line.count(" | ") == 3, line


def test_cli_reference_imports_no_torch():
    """Building the parsers stays light: the CLIs import torch only when they run."""
    code = ("import sys; from clod_adapter.cli.reference import cli_reference; cli_reference(); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert out.stdout.strip() == "False"
