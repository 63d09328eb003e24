"""The fleet path's rates on this machine: a robot's NATS destination into JetStream, then `dc ingest`
workers into PostgreSQL, against PostgreSQL's own COPY of the same rows.

    .venv/bin/python benchmarks/fleet.py [--records 20000] [--workers 1 2 4] [--cluster]

A throw-away nats-server (or, with --cluster, a 3-node cluster and a stream with 3 replicas) and a
PostgreSQL on loopback. The records (~250 bytes of JSON) are published by the NATS destination in
batches of 500, as a robot's sender would, each acknowledged by the stream. Then, for each worker
count, that many `dc ingest` processes share a new durable consumer and write the whole stream into
a table of their own; the time from their start to the last row is the ingest rate. Last, the same
rows are loaded with COPY into a table with the same unique record_id index. Everything runs on
this one machine: the workers, the server and PostgreSQL share its cores.

    .venv/bin/python benchmarks/fleet.py --robots 1 4 [--jobs default robot] [--window 120]

The robots' side instead: for each job (params/default.yaml; params/benchmarks/robot_footprint.yaml,
the robot job, beside a ``dc sim --loop`` of its own) and each robot count, that many DC stacks run
as `dc-bringup --single-process`, each in a ROS domain and folder of its own, their destinations
replaced by one NATS destination into a local nats-server (subject ``dc.<robot>.<name>``). Over
``--window`` seconds (after DC is up and ``--settle`` more), the records and bytes (the JSON
stored in the stream) of each robot are read back from the stream, and the CPU of each DC process
tree (and of each simulator, apart) from /proc: records and bytes per robot and day, CPU % of one
core per robot, and the machine's busy %. Run it with ``nice -n 10`` on a shared machine, with
``DC_TEST_DOMAIN_SLOT`` set to your test slot: the robots then take that slot's ROS domains, which
the other engineers' tests do not use.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from dc_bringup.local_servers.nats import NatsCluster, NatsNode  # noqa: E402
from dc_bringup.local_servers.postgres import PostgresServer  # noqa: E402
from dc_core.destination import OutgoingRecord, RetryableError  # noqa: E402
from dc_core.params import parse_params  # noqa: E402
from dc_core.testing import FakeContext  # noqa: E402
from dc_destinations.jetstream import Nats, NatsParams  # noqa: E402
from dc_destinations.record_ids import new_record_id  # noqa: E402

JOBS = {"default": REPO / "params" / "default.yaml", "robot": REPO / "params" / "benchmarks" / "robot_footprint.yaml"}


def records(count: int) -> list[OutgoingRecord]:
    made = []
    for n in range(count):
        rid = new_record_id()
        data = {
            "date": 1_700_000_000 + n / 100,
            "name": "system",
            "robot_name": f"robot-{n % 100:03d}",
            "run_id": "3",
            "cpu": {"percent": 12.5, "load": [0.5, 0.4, 0.3]},
            "memory": {"used": 123456789, "percent": 45.6},
            "record_id": rid,
        }
        made.append(OutgoingRecord(rid, "/dc/measurement/system", 1_700_000_000_000_000_000 + n, data))
    return made


def connect(pg: PostgresServer) -> Any:
    import psycopg

    s = pg.settings()
    return psycopg.connect(
        host=str(s["host"]), port=int(s["port"]), user=str(s["user"]), password=str(s["password"]), dbname="dc"
    )


def count(pg: PostgresServer, table: str) -> int:
    with connect(pg) as connection:
        try:
            row = connection.execute(f"SELECT count(*) FROM {table}").fetchone()
        except Exception:
            return 0
    return int(row[0]) if row else 0


def ingest(pg: PostgresServer, servers: list[str], workers: int, total: int, folder: Path) -> float:
    """Seconds for ``workers`` dc ingest processes to write the whole stream into a table of their own."""
    table = f"fleet_w{workers}"
    params = folder / f"{table}.yaml"
    s = pg.settings()
    params.write_text(
        "destination_server:\n  ros__parameters:\n    destination_plugins: [warehouse]\n"
        "    flb: {flush: 0.05, http_server: false}\n"
        "    warehouse:\n      plugin: dc_destinations/PgSQL\n      inputs: [/dc/measurement/system]\n"
        f"      host: 127.0.0.1\n      port: {s['port']}\n      user: {s['user']}\n      database: dc\n"
        f"      table: {table}\n      batch_size: 1000\n"
    )
    env = {**os.environ, "PGPASSWORD": str(s["password"]), "PYTHONPATH": str(REPO)}
    started = time.monotonic()
    processes = [
        subprocess.Popen(
            [
                *(sys.executable, "-m", "dc_bringup.cli", "ingest", str(params), "--servers", ",".join(servers)),
                *("--consumer", table, "--batch", "1000", "--storage-path", str(folder / f"{table}-{i}")),
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=(folder / f"{table}-{i}.log").open("wb"),
        )
        for i in range(workers)
    ]
    try:
        while count(pg, table) < total:
            if any(p.poll() is not None for p in processes):
                raise RuntimeError(f"a worker exited: see {folder}")
            time.sleep(0.1)
        return time.monotonic() - started
    finally:
        for p in processes:
            p.send_signal(signal.SIGTERM)
        for p in processes:
            p.wait(30)


def copy_rate(pg: PostgresServer, batch: list[OutgoingRecord]) -> float:
    """Seconds for COPY to load the rows into a table like the destination's (record_id unique)."""
    with connect(pg) as connection:
        connection.execute("CREATE TABLE fleet_copy (tag text, time timestamptz, data jsonb, record_id text UNIQUE)")
        connection.commit()
        started = time.monotonic()
        for start in range(0, len(batch), 1000):
            with (
                connection.cursor() as cursor,
                cursor.copy("COPY fleet_copy (tag, time, data, record_id) FROM STDIN") as copy,
            ):
                for r in batch[start : start + 1000]:
                    copy.write_row(("warehouse", "2023-11-14T22:13:20Z", r.to_json(), r.record_id))
            connection.commit()
        return time.monotonic() - started


def robot_params(job: Path, robot: str, nats_url: str) -> str:
    """``job``'s parameters with its destinations replaced by one NATS destination publishing on dc.<robot>.<name>."""
    import yaml

    params = yaml.safe_load(job.read_text())
    measurements = params["measurement_server"]["ros__parameters"]
    topics = []
    for name in measurements["measurement_plugins"]:
        measurements[name]["tags"] = ["fleet"]
        topics.append(measurements[name].get("topic_output", f"/dc/measurement/{name}"))
    destinations = params["destination_server"]["ros__parameters"]
    for name in destinations.pop("destination_plugins"):
        destinations.pop(name)
    destinations["destination_plugins"] = ["fleet"]
    destinations["fleet"] = {
        "plugin": "dc_destinations/NATS",
        "servers": [nats_url],
        "stream": "DC",
        "create_stream": True,
        "subject": f"dc.{robot}.{{name}}",
        "inputs": topics,
    }
    return str(yaml.safe_dump(params, sort_keys=False))


def stream_last_sequence(url: str) -> int:
    import asyncio

    import nats

    async def last() -> int:
        nc = await nats.connect(servers=[url])
        try:
            info = await nc.jetstream().stream_info("DC")
            return int(info.state.last_seq or 0)
        finally:
            await nc.close()

    return asyncio.run(last())


def stream_between(url: str, after: int, until: int) -> dict[str, tuple[int, int]]:
    """Per robot (the subject's second token): (messages, bytes of their JSON) of stream sequences after..until."""
    import asyncio

    import nats
    from nats.js.api import ConsumerConfig, DeliverPolicy

    async def read() -> dict[str, tuple[int, int]]:
        counts: dict[str, tuple[int, int]] = {}
        nc = await nats.connect(servers=[url])
        try:
            config = ConsumerConfig(deliver_policy=DeliverPolicy.BY_START_SEQUENCE, opt_start_seq=after + 1)
            sub = await nc.jetstream().pull_subscribe("dc.>", stream="DC", config=config)
            seen = after
            while seen < until:
                for msg in await sub.fetch(500, timeout=10):
                    seq = msg.metadata.sequence.stream
                    seen = max(seen, seq)
                    if seq <= until:
                        robot = msg.subject.split(".")[1]
                        n, size = counts.get(robot, (0, 0))
                        counts[robot] = (n + 1, size + len(msg.data))
                    await msg.ack()
        finally:
            await nc.close()
        return counts

    return asyncio.run(read())


def cpu_ticks(tree: dict[Any, Any]) -> int:
    return sum(r.cpu_ticks + r.reaped_ticks for r in tree.values())


def span(values: list[Any], spec: str = "") -> str:
    """The lowest and highest of ``values`` ("a to b"), or the one value, or "none"."""
    if not values:
        return "none"
    low, high = format(min(values), spec), format(max(values), spec)
    return low if low == high else f"{low} to {high}"


def robot_domains() -> list[int]:
    """The ROS domains the robots may take: with ``DC_TEST_DOMAIN_SLOT=k/n`` (set for an engineer's
    tests on a shared machine, tests/domains.py) that slot's own, which other sessions' tests never
    use; else 120..232 from a random start (domain ids end at 232)."""
    import random

    slot, _, slots = os.environ.get("DC_TEST_DOMAIN_SLOT", "").partition("/")
    if slot.isdigit() and slots.isdigit() and int(slots) > 0:
        return [d for d in range(21, 233) if d % int(slots) == int(slot) % int(slots)]
    start = random.randint(120, 232)
    return [*range(start, 233), *range(120, start)]


def quiet_domain(domains: Any, home: Path) -> int:
    """The next of ``domains`` where no ROS node answers (another DC there would drive our servers)."""
    from benchmarks import footprint

    for domain in domains:
        try:
            return footprint.quiet_domain(domain, footprint.environment(home, domain), tries=1)
        except RuntimeError:
            continue
    raise RuntimeError("no quiet ROS domain left for the robots")


def robots(args: argparse.Namespace) -> int:
    """The robots' side: see the module documentation."""
    import contextlib

    from benchmarks import footprint

    folder = Path(tempfile.mkdtemp(prefix="dc-fleet-robots-"))
    nats = NatsNode(folder / "nats")
    hz = os.sysconf("SC_CLK_TCK")
    rows = []
    try:
        nats.start()
        for job in args.jobs:
            for count in args.robots:
                with contextlib.ExitStack() as stack:
                    bringups, sims = [], []
                    domains = iter(robot_domains())
                    for i in range(count):
                        robot = f"{job}-n{count}-r{i}"
                        home = folder / robot
                        home.mkdir()
                        domain = quiet_domain(domains, home)
                        env = footprint.environment(home, domain)
                        params = home / "params.yaml"
                        params.write_text(robot_params(JOBS[job], robot, nats.url))
                        if job == "robot":
                            sim = [footprint.venv_script("dc"), "sim", "--loop"]
                            sims.append(stack.enter_context(footprint.started(sim, env, home, home / "sim.log", 30)))
                        bringup = [footprint.venv_script("dc-bringup"), str(params), "--single-process"]
                        bringups.append(
                            stack.enter_context(footprint.started(bringup, env, home, home / "bringup.log", 60))
                        )
                    for bringup in bringups:
                        footprint.wait_for_up(bringup, args.up_timeout)
                    time.sleep(args.settle)
                    first = stream_last_sequence(nats.url)
                    dc_before = [cpu_ticks(b.read()) for b in bringups]
                    sim_before = [cpu_ticks(s.read()) for s in sims]
                    busy_before, total_before = footprint.machine_ticks()
                    started = time.monotonic()
                    time.sleep(args.window)
                    seconds = time.monotonic() - started
                    last = stream_last_sequence(nats.url)
                    dc_after = [cpu_ticks(b.read()) for b in bringups]
                    sim_after = [cpu_ticks(s.read()) for s in sims]
                    busy_after, total_after = footprint.machine_ticks()
                counts = stream_between(nats.url, first, last)
                per_robot = [counts.get(f"{job}-n{count}-r{i}", (0, 0)) for i in range(count)]
                cpu = [100 * (a - b) / hz / seconds for a, b in zip(dc_after, dc_before, strict=True)]
                sim_cpu = [100 * (a - b) / hz / seconds for a, b in zip(sim_after, sim_before, strict=True)]
                row = {
                    "job": job,
                    "robots": count,
                    "window_s": round(seconds, 1),
                    "records_per_day": [round(n / seconds * 86400) for n, _ in per_robot],
                    "mb_per_day": [round(size / seconds * 86400 / 1e6, 1) for _, size in per_robot],
                    "dc_cpu_percent": [round(c, 1) for c in cpu],
                    "sim_cpu_percent": [round(c, 1) for c in sim_cpu],
                    "machine_busy_percent": round(100 * (busy_after - busy_before) / (total_after - total_before), 1),
                }
                rows.append(row)
                print(row, flush=True)
    finally:
        nats.stop()
        shutil.rmtree(folder, ignore_errors=True)
    print()
    print("| job | robots | records/day per robot | MB/day per robot | DC CPU % per robot | sim CPU % | busy % |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['job']} | {r['robots']} | {span(r['records_per_day'], ',')} | {span(r['mb_per_day'])} | "
            f"{span(r['dc_cpu_percent'])} | {span(r['sim_cpu_percent'])} | {r['machine_busy_percent']} |"
        )
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=20000)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--cluster", action="store_true", help="a 3-node cluster and a stream with 3 replicas")
    parser.add_argument("--robots", type=int, nargs="+", help="the robots' side instead, with these robot counts")
    parser.add_argument("--jobs", nargs="+", choices=sorted(JOBS), default=["default", "robot"])
    parser.add_argument("--window", type=float, default=120.0, help="seconds measured, per job and robot count")
    parser.add_argument("--settle", type=float, default=10.0, help="seconds after DC is up before the window")
    parser.add_argument("--up-timeout", type=float, default=180.0, help="seconds for each robot's DC to come up")
    args = parser.parse_args()
    if args.robots:
        return robots(args)
    folder = Path(tempfile.mkdtemp(prefix="dc-fleet-bench-"))
    # Its own temporary folder: as root, PostgreSQL runs as user postgres, who cannot enter `folder`.
    pg_folder = Path(tempfile.mkdtemp(prefix="dc-fleet-bench-pg-"))
    pg = PostgresServer(pg_folder, password="bench-only")
    nats: NatsCluster | NatsNode = NatsCluster(folder / "nats") if args.cluster else NatsNode(folder / "nats")
    servers = nats.urls if isinstance(nats, NatsCluster) else [nats.url]
    batch = records(args.records)
    size = sum(len(r.to_json()) for r in batch) / len(batch)
    try:
        pg.start()
        nats.start()
        settings = {
            "servers": servers,
            "stream": "DC",
            "create_stream": True,
            "stream_replicas": 3 if args.cluster else 1,
            "subject": "dc.{robot_name}.{name}",
        }
        robot = Nats(FakeContext(name="fleet"), parse_params(NatsParams, settings, "destination_server.fleet"))
        robot.on_configure()
        deadline = time.monotonic() + 60
        while True:  # a cluster just started elects its JetStream leader first: retried, as DC's sender would
            try:
                assert robot.send(batch[:1]) is None
                break
            except RetryableError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        started = time.monotonic()
        for start in range(0, len(batch), 500):
            assert robot.send(batch[start : start + 500]) is None
        publish = time.monotonic() - started
        robot.on_cleanup()
        replicas = "3 replicas, 3 nodes" if args.cluster else "1 node"
        print(f"{args.records} records of {size:.0f} bytes of JSON; JetStream file store, {replicas}")
        print(f"robot → stream (NATS destination, batches of 500, each acked): {args.records / publish:,.0f} records/s")
        copy = copy_rate(pg, batch)
        print(f"PostgreSQL COPY of the same rows, 1000 per commit: {args.records / copy:,.0f} rows/s")
        for workers in args.workers:
            seconds = ingest(pg, servers, workers, args.records, folder)
            rate = args.records / seconds
            print(
                f"stream → PostgreSQL, {workers} dc ingest worker(s): {rate:,.0f} records/s "
                f"({rate / (args.records / copy):.2f} of COPY; includes the workers' start, ~1 s)"
            )
    finally:
        nats.stop()
        pg.stop()
        shutil.rmtree(folder, ignore_errors=True)
        shutil.rmtree(pg_folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
