"""One inserting client of the chaos test (`test_chaos.py`), run as its own process:

    python -m tests.buffer_service.chaos_client PORT ACTOR COUNT ACKED_FILE

inserts episodes ``make_episode(ACTOR, seq, t=3)`` for seq in 0..COUNT-1, one per request,
retrying through service restarts, and appends each seq to ACKED_FILE once it is
acknowledged (then "done"; or "error: ..." if the service refused one). An insert refused
with ``storage_full`` (a full disk) is retried after a pause, as an actor would, and
noted as "full" in the file.
"""

from __future__ import annotations

import sys
import time

from buffer_service.client import BufferClient, BufferServiceError
from tests.buffer_service.conftest import SCHEMA, make_episode


def insert(client: BufferClient, actor: int, seq: int, out) -> None:
    while True:
        try:
            client.insert([make_episode(actor, seq, t=3)])
            return
        except BufferServiceError as e:
            if e.code != "storage_full":
                raise
            out.write("full\n")
            time.sleep(0.05)


def main(port: int, actor: int, count: int, acked_file: str) -> int:
    client = BufferClient(
        port=port, schema=SCHEMA, backoff_s=0.05, max_backoff_s=0.5, max_retries=2000
    )
    with open(acked_file, "a", buffering=1) as out:
        try:
            for seq in range(count):
                insert(client, actor, seq, out)
                out.write(f"{seq}\n")
        except Exception as e:  # reported to the test through the file
            out.write(f"error: {type(e).__name__}: {e}\n")
            return 1
        out.write("done\n")
    client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]))
