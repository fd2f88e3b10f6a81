"""`reflab demo` runs exactly README's stepwise commands for the simulated lab (issue 14)."""
import re
import shlex
from pathlib import Path

from app.commands.demo import commands

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_commands() -> list[list[str]]:
    """The command block of README's "The simulated lab step by step", each line as argv."""
    text = README.read_text()
    section = text.split("## The simulated lab step by step", 1)[1].split("\n## ", 1)[0]
    lines = re.findall(r"^    reflab (.+)$", section, flags=re.M)
    return [shlex.split(line) for line in lines]


def test_demo_runs_readmes_commands():
    documented = readme_commands()
    assert documented[0] == ["demo", "demo-workspace", "--truth-only"]
    assert documented[1:] == [argv for _, argv in commands("demo-workspace")]
