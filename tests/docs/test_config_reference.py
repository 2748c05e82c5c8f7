"""docs/config-reference.md is what `python -m cluster.config.reference` prints now."""

from pathlib import Path

from cluster.config.reference import attribute_docs, main, render
from cluster.config.train import RunConfig

REFERENCE = Path(__file__).resolve().parents[2] / "docs" / "config-reference.md"
REGENERATE = "python -m cluster.config.reference --out docs/config-reference.md"


def test_the_committed_reference_is_up_to_date():
    assert REFERENCE.read_text() == render(), f"docs/config-reference.md is stale: {REGENERATE}"


def test_every_key_is_documented():
    assert "(not documented)" not in render()


def test_attribute_docs_joins_continuation_lines_and_stops_at_the_section_end():
    docs = attribute_docs(RunConfig)
    assert docs["t_max"] == "env steps to train for."
    assert docs["device"].startswith("torch device of the learner") and docs["device"].endswith(
        "always act on the CPU."
    )


def test_main_writes_the_file(tmp_path):
    out = tmp_path / "ref.md"
    assert main(["--out", str(out)]) == 0
    assert out.read_text() == render()
