"""Compare two folders of evaluation logs line by line, every field but the commit and the
wall time: prints IDENTICAL or the first difference per file; exit 1 if any differ."""

import json
import sys
from pathlib import Path

VOLATILE = {"commit", "wall_s"}


def lines(path: Path) -> list[dict]:
    return [
        {k: v for k, v in json.loads(line).items() if k not in VOLATILE}
        for line in path.read_text().splitlines()
    ]


def main(a: str, b: str) -> int:
    names = sorted(
        {p.name for p in Path(a).glob("*.jsonl")} | {p.name for p in Path(b).glob("*.jsonl")}
    )
    differ = 0
    for name in names:
        la, lb = (lines(Path(d) / name) if (Path(d) / name).exists() else [] for d in (a, b))
        if la == lb:
            print(f"{name}: {len(la)} evaluations, IDENTICAL")
            continue
        differ = 1
        first = next(
            (i for i, (x, y) in enumerate(zip(la, lb, strict=False)) if x != y),
            min(len(la), len(lb)),
        )
        print(f"{name}: DIFFER from evaluation {first} ({len(la)} and {len(lb)} evaluations)")
    return differ


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
