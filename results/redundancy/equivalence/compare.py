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
    differ = 0
    for fa in sorted(Path(a).glob("*.jsonl")):
        la, lb = lines(fa), lines(Path(b) / fa.name)
        if la == lb:
            print(f"{fa.name}: {len(la)} evaluations, IDENTICAL")
            continue
        differ = 1
        first = (
            next((x, y) for x, y in zip(la, lb, strict=False) if x != y)
            if len(la) == len(lb)
            else (len(la), len(lb))
        )
        print(f"{fa.name}: DIFFER, first: {first}")
    return differ


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
