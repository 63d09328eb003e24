"""Operator tools on the buffer file (``dc buffer list|show|replay|purge|stats|salvage``).

They open the SQLite file directly with their own connection, which WAL allows while
``destination_server`` runs: a replayed dead letter goes back to the end of its destination's
queue and the running server's sender picks it up at its next round (after its current backoff,
if the destination is failing). These tools never move or repair a damaged file; the server does
that at its next start. ``salvage`` reads a damaged (set-aside) file and puts every row it can
read into a buffer, the running server's included.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any, TextIO

from dc_core.config import load_params
from dc_core.errors import ConfigError, DcError
from dc_core.paths import expand_env
from dc_destinations.buffer import FILE_NAME, DeadLetter, QueueStats, SqliteBuffer
from dc_destinations.salvage import SalvageReport
from dc_destinations.storage import default_storage_dir


class BufferAdminError(DcError):
    """The buffer cannot be found or opened, or the request is incomplete."""


def storage_file(storage_path: str = "", params_file: str = "", namespace: str = "/") -> Path:
    """The buffer file: ``storage_path``, else a parameter file's ``flb.storage_path``, else the default
    folder of the destination server in ``namespace`` and this environment's ROS_DOMAIN_ID."""
    if not storage_path and params_file:
        storage_path = _storage_path_from_params(Path(params_file), namespace)
    directory = Path(expand_env(storage_path)).expanduser() if storage_path else default_storage_dir(namespace)
    return directory / FILE_NAME if directory.suffix != ".sqlite3" else directory


def _storage_path_from_params(params_file: Path, namespace: str = "/") -> str:
    # Read as the server reads it (a Nav2-style /r1/destination_server:, flb.storage_path dotted).
    try:
        parameters = load_params(params_file, namespace).raw.get("destination_server", {})
    except ConfigError:
        return ""  # no destination_server there: the default folder, as without --params
    flb = parameters.get("flb", {})
    value = flb.get("storage_path", "") if isinstance(flb, dict) else ""
    return str(value or "")


def open_buffer(path: Path) -> SqliteBuffer:
    if not path.exists():
        raise BufferAdminError(
            f"no buffer at {path} (set --storage-path or --params; or --namespace and ROS_DOMAIN_ID as the server had)"
        )
    return SqliteBuffer(path, repair=False)


def queue_stats(path: Path) -> list[QueueStats]:
    with contextlib.closing(open_buffer(path)) as buffer:
        return [buffer.stats(name) for name in buffer.destinations()]


def hop_loss_totals(path: Path) -> dict[str, tuple[int, int]]:
    """Per input topic, the records every run counted lost before destination_server, and in how many gaps."""
    with contextlib.closing(open_buffer(path)) as buffer:
        return buffer.hop_loss_totals()


def list_dead_letters(path: Path, destination: str | None = None, limit: int = 1000) -> list[DeadLetter]:
    with contextlib.closing(open_buffer(path)) as buffer:
        return buffer.list_dead_letters(destination, limit=limit)


def show_dead_letter(path: Path, dead_letter_id: int) -> DeadLetter | None:
    with contextlib.closing(open_buffer(path)) as buffer:
        return buffer.get_dead_letter(dead_letter_id)


def replay(path: Path, ids: Sequence[int] | None = None, destination: str | None = None) -> int:
    """Move dead letters back to their queues (all of them when neither ``ids`` nor ``destination``)."""
    with contextlib.closing(open_buffer(path)) as buffer:
        return buffer.replay_dead_letters(destination, ids)


def purge(path: Path, ids: Sequence[int] | None = None, destination: str | None = None) -> int:
    """Delete dead letters for good (all of them when neither ``ids`` nor ``destination``)."""
    with contextlib.closing(open_buffer(path)) as buffer:
        return buffer.purge_dead_letters(destination, ids)


def salvage(source: Path, into: Path) -> SalvageReport:
    """Put every readable record and dead letter of the buffer file ``source`` into the buffer ``into``
    (created if needed); ``source`` is only read."""
    if not source.is_file():
        raise BufferAdminError(f"no file {source}")
    with contextlib.closing(SqliteBuffer(into, repair=False)) as buffer:
        return buffer.salvage(source)


def _utc(ns: int) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ns / 1e9))


def _short(text: str, width: int) -> str:
    text = " ".join(text.split())
    return text if len(text) <= width else text[: width - 1] + "…"


def run_cli(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    """``dc buffer``: ``args`` has action, ids, storage_path, params, destination and all."""
    try:
        if args.action == "salvage":
            if len(args.ids) != 1:
                raise BufferAdminError("dc buffer salvage: give the set-aside file (delivery.sqlite3.corrupt-...)")
            into = storage_file(getattr(args, "into", "") or args.storage_path, args.params, args.namespace)
            report = salvage(Path(args.ids[0]), into)
            print(f"salvaged {args.ids[0]} into {into}: {report.summary()}", file=out)
            return 0
        path = storage_file(args.storage_path, args.params, args.namespace)
        destination = args.destination or None
        ids = [int(i) for i in args.ids] if args.ids else None
        if args.action == "stats":
            _print_stats(path, queue_stats(path), out)
            for topic, (missing, gaps) in hop_loss_totals(path).items():
                if missing:
                    print(f"lost before destination_server, all runs: {missing} on {topic} ({gaps} gaps)", file=out)
        elif args.action == "list":
            letters = list_dead_letters(path, destination)
            if getattr(args, "json", False):
                for listed in letters:
                    print(json.dumps(_as_json(listed), ensure_ascii=False), file=out)
            else:
                _print_list(letters, out)
        elif args.action == "show":
            if not ids:
                raise BufferAdminError("dc buffer show: give one or more dead-letter ids (see dc buffer list)")
            for dead_letter_id in ids:
                letter = show_dead_letter(path, dead_letter_id)
                if letter is None:
                    raise BufferAdminError(f"no dead letter {dead_letter_id}")
                print(json.dumps(_as_json(letter), indent=2, ensure_ascii=False), file=out)
        elif args.action in ("replay", "purge"):
            if ids is None and destination is None and not args.all:
                raise BufferAdminError(f"dc buffer {args.action}: give ids, --destination or --all")
            if args.action == "replay":
                print(f"replayed {replay(path, ids, destination)} dead letter(s) into their queues", file=out)
            else:
                print(f"purged {purge(path, ids, destination)} dead letter(s)", file=out)
        else:
            raise BufferAdminError(f"unknown action {args.action}")
    except ValueError as exc:
        print(f"dc buffer: ids are numbers ({exc})", file=sys.stderr)
        return 2
    except (DcError, OSError) as exc:
        print(f"dc buffer: {exc}", file=sys.stderr)
        return 1
    return 0


def _as_json(letter: DeadLetter) -> dict[str, Any]:
    values = asdict(letter)
    with contextlib.suppress(ValueError):
        values["payload"] = json.loads(letter.payload)
    values["failed_at"] = _utc(letter.failed_ns)
    values["enqueued_at"] = _utc(letter.enqueued_ns)
    return values


def _print_list(letters: list[DeadLetter], out: TextIO) -> None:
    if not letters:
        print("no dead letters", file=out)
        return
    print(
        f"{'id':>8}  {'destination':<16} {'failed at (UTC)':<21} {'tries':>5}  {'record_id':<36}  error",
        file=out,
    )
    for d in letters:
        print(
            f"{d.id:>8}  {_short(d.destination, 16):<16} {_utc(d.failed_ns):<21} {d.attempts:>5}  "
            f"{d.record_id:<36}  {_short(d.error, 60)}",
            file=out,
        )


def _print_stats(path: Path, stats: list[QueueStats], out: TextIO) -> None:
    print(f"buffer {path}", file=out)
    print(
        f"{'destination':<20}{'buffered':>10}{'bytes':>12}{'oldest (UTC)':>22}{'dead':>7}"
        f"{'received':>11}{'sent':>11}{'dropped':>9}",
        file=out,
    )
    for s in stats:
        oldest = _utc(s.oldest_enqueued_ns) if s.oldest_enqueued_ns is not None else "-"
        print(
            f"{_short(s.destination, 19):<20}{s.rows:>10}{s.bytes:>12}{oldest:>22}{s.dead_letters:>7}"
            f"{s.received_total:>11}{s.sent_total:>11}{s.dropped_total:>9}",
            file=out,
        )
