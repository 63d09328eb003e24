"""destination_server's CPU per 1,000 records at a paced 1,000/s, for several code trees, round by round.

Single runs of end_to_end.py swing by ±20 % with the machine's load (docs/performance.md). Here the
trees take turns within each round (their order reversed every other round), the bare receivers
(EventsExecutor, DC's intake loop) are measured in every round, and the medians are compared:

    git worktree add /tmp/before 249678d
    .venv/bin/python benchmarks/ab_paced.py --rounds 4 before=/tmp/before after=.

Each tree's server is started from that tree (``python -m dc_destinations.server`` with the tree as
working directory, so its own packages are imported); the publisher and the bare receivers are
end_to_end.py's, from this checkout. Results (every run, medians, ratios) go to ``--json``.
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import end_to_end as e2e  # a sibling script, not a package

BARE = ("events", "intake")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("trees", nargs="+", help="NAME=PATH of a checkout whose destination_server is measured")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--records", type=int, default=10_000, help="records of each paced run")
    parser.add_argument("--sync", default="normal", choices=["normal", "full"], help="storage_sync of the server")
    parser.add_argument("--domain", type=int, default=random.randint(150, 230), help="ROS_DOMAIN_ID")
    parser.add_argument("--json", default=str(e2e.REPO / "benchmarks" / "results" / "ab_paced.json"))
    args = parser.parse_args()
    trees = e2e.checkouts(parser, args.trees)

    cpu: dict[str, list[float]] = {name: [] for name in (*BARE, *trees)}
    started = datetime.now(UTC)
    with tempfile.TemporaryDirectory(prefix="dc-ab-") as tmp:
        bench = e2e.Bench(Path(tmp), args.domain)
        for round_ in range(args.rounds):
            order = list(trees) if round_ % 2 == 0 else list(reversed(trees))
            for kind in BARE:
                cpu[kind].append(e2e.transport(bench, kind, args.records, 1000.0).cpu_ms_per_1000)
            for name in order:
                e2e.REPO = trees[name]  # the server child's working directory
                flow = e2e.intake(bench, args.sync, args.records, 1000.0, True)
                if flow.delivered != flow.sent:
                    raise RuntimeError(f"{name}: {flow.sent - flow.delivered} records not delivered")
                cpu[name].append(flow.cpu_ms_per_1000)
            line = ", ".join(f"{name} {values[-1]:.0f}" for name, values in cpu.items())
            print(f"round {round_ + 1}: {line} ms CPU per 1,000 records", flush=True)

    medians = {name: statistics.median(values) for name, values in cpu.items()}
    cheapest = min(medians[kind] for kind in BARE)
    print(f"\nmedians of {args.rounds} rounds, paced 1,000 records/s, storage_sync {args.sync}:")
    for name, value in medians.items():
        ratio = "" if name in BARE else f"   {value / cheapest:.2f}x the cheapest bare receiver"
        print(f"  {name:<12} {value:6.0f} ms per 1,000{ratio}")
    document = {
        "date": started.isoformat(timespec="seconds"),
        "settings": {"rounds": args.rounds, "records": args.records, "sync": args.sync},
        "trees": {name: str(path) for name, path in trees.items()},
        "cpu_ms_per_1000": cpu,
        "medians": medians,
        "ratios_to_cheapest_bare": {name: medians[name] / cheapest for name in trees},
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(document, indent=2) + "\n")
    print(f"\nJSON: {args.json}")


if __name__ == "__main__":
    main()
