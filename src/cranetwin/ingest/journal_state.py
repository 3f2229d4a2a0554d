"""The send journal's small files: ``state`` (epoch, release watermark, owner) and the dead
letters in ``rejected.log`` (datagrams the server refused, one JSON line each)."""

from __future__ import annotations

import json
import secrets
from datetime import UTC, datetime
from pathlib import Path

from cranetwin.ingest.journal_files import MAX_SEQ, SenderError

STATE_FORMAT = "cranetwin-send-journal"


def new_epoch() -> int:
    """A random epoch in 1 … 2**63 − 1."""
    while True:
        e = secrets.randbits(63)
        if e:
            return e


def state_body(epoch: int, released: int, owner: str | None) -> bytes:
    """The ``state`` file's content."""
    return (json.dumps({"format": STATE_FORMAT, "version": 1, "epoch": epoch,
                        "released": released, "owner": owner}) + "\n").encode()


def read_state(directory: Path) -> tuple[int, int, str | None]:
    """(epoch, released watermark, owner) from ``directory/state``.

    Raises:
        SenderError: the file cannot be read or is not a valid state.
    """
    path = directory / "state"
    try:
        with open(path, "rb") as f:
            raw = f.read(1 << 16)
    except OSError as exc:
        raise SenderError(f"cannot read the journal state {path}: {exc}") from exc
    try:
        st = json.loads(raw)
        ok = (isinstance(st, dict) and st.get("format") == STATE_FORMAT
              and st.get("version") == 1)
        epoch, released, owner = st["epoch"], st["released"], st.get("owner")
        ok = ok and type(epoch) is int and 0 < epoch < MAX_SEQ
        ok = ok and type(released) is int and 0 <= released < MAX_SEQ
        ok = ok and (owner is None or isinstance(owner, str))
    except (ValueError, TypeError, KeyError, AttributeError):
        ok = False
    if not ok:
        raise SenderError(
            f"the journal state {path} is corrupt ({raw[:80]!r}); the datagrams in "
            f"{directory} cannot be sent without it. Repair it or move the directory "
            "away to start a new journal")
    return epoch, released, owner


def rejected_line(epoch: int, seq: int, reason: str, datagram: bytes) -> bytes:
    """One dead letter: a JSON line with time, epoch, seq, reason and the datagram in hex."""
    return (json.dumps({
        "time": datetime.now(UTC).isoformat(timespec="milliseconds"),
        "epoch": epoch, "seq": seq, "reason": str(reason),
        "bytes": len(datagram), "datagram": bytes(datagram).hex()}) + "\n").encode()


def load_rejected(path: Path, epoch: int, start: int, end: int) -> set[int]:
    """Seqs of ``epoch`` in [start, end) that ``path`` (rejected.log) lists as refused.

    Raises:
        SenderError: the file exists but cannot be read.
    """
    try:
        with open(path, "rb") as f:
            lines = f.read().splitlines()
    except FileNotFoundError:
        return set()
    except OSError as exc:
        raise SenderError(f"cannot read {path}: {exc}") from exc
    out: set[int] = set()
    for line in lines:
        try:
            rec = json.loads(line)
            if rec["epoch"] == epoch and isinstance(rec["seq"], int):
                if start <= rec["seq"] < end:
                    out.add(rec["seq"])
        except (ValueError, TypeError, KeyError):
            continue  # a torn last line, or edited by the operator
    return out
