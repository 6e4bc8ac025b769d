"""`--help` and argument errors answer at once: no command imports torch to describe itself."""

import subprocess
import sys
from pathlib import Path

import pytest

from crestereo_pp.cli.main import COMMANDS
from crestereo_pp.cli.options import MODEL_NAMES, TWO_PASS_CHOICES
from crestereo_pp.inference.options import TWO_PASS_CHOICES as MODEL_TWO_PASS_CHOICES
from crestereo_pp.model.config import MODEL_NAMES as MODEL_CONFIG_NAMES

REPO = Path(__file__).resolve().parents[2]

# Runs the CLI, then says on its last line whether torch was imported.
SCRIPT = """
import sys
from crestereo_pp.cli.main import main
try:
    raise SystemExit(main(sys.argv[1:]))  # as the installed entry point does
finally:
    print("torch imported:", "torch" in sys.modules, file=sys.stderr)
"""


def run_cli(*arguments: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", SCRIPT, *arguments], cwd=REPO, capture_output=True, text=True, check=False
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    ("arguments", "status"),
    [
        ((), 2),  # no command
        (("--help",), 0),
        *(((name, "--help"), 0) for name in COMMANDS if name != "train"),
        (("predict", "left.png"), 2),  # no right image, no --output
        (("predict", "l.png", "r.png", "-o", "d.pfm", "--two-pass", "maybe"), 2),
        (("eval",), 2),
        (("prepare", "--model", "huge"), 2),
    ],
)
def test_help_and_argument_errors_do_not_import_torch(arguments, status):
    # `train --help` does: its options come from TrainConfig, whose scene settings live beside the renderer.
    done = run_cli(*arguments)
    assert done.returncode == status, done.stderr
    assert done.stderr.splitlines()[-1] == "torch imported: False"


def test_the_cli_spells_model_names_and_two_pass_choices_as_the_model_does():
    assert (MODEL_NAMES, TWO_PASS_CHOICES) == (MODEL_CONFIG_NAMES, MODEL_TWO_PASS_CHOICES)
