"""The destination docs/plugin_development.md writes on the driver, run as the page shows it.

Its code block is loaded as a module; it posts to a real HTTP(S) receiver on loopback.
"""

from __future__ import annotations

import json
import re
import sys
import types
from pathlib import Path
from typing import Any

import pytest

from dc_core.destination import OutgoingRecord, RejectedError, RetryableError
from dc_core.testing import PluginHarness
from dc_destinations.http.test_http import RetryAfterServer
from tests.http_receiver import Receiver, Request
from tests.tls_pki import Pki, make_pki

PAGE = Path(__file__).parent.parent / "docs" / "plugin_development.md"
HEADER = "# my_robot_dc/ingest/__init__.py"
TOKEN = "tok-3f9a7c21e5"
BATCH = [OutgoingRecord(f"id-{n}", "/dc/measurement/cpu", n, {"n": n}) for n in range(3)]


def example_source() -> str:
    blocks: list[str] = re.findall(r"```python\n(.*?)```", PAGE.read_text(encoding="utf-8"), flags=re.DOTALL)
    (source,) = [b for b in blocks if b.startswith(HEADER)]
    return source


@pytest.fixture(scope="module")
def ingest() -> Any:
    module = types.ModuleType("doc_example_ingest")
    sys.modules[module.__name__] = module  # dataclasses look their module up
    try:
        exec(compile(example_source(), str(PAGE), "exec"), module.__dict__)
        yield module
    finally:
        del sys.modules[module.__name__]


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("tls"))


def test_the_example_is_shorter_than_the_http_destination() -> None:
    http = Path(__file__).parent.parent / "dc_destinations" / "http" / "__init__.py"
    assert len(example_source().splitlines()) < len(http.read_text(encoding="utf-8").splitlines()) / 4


def test_the_example_delivers_over_one_kept_connection_and_closes_it_on_deactivate(ingest: Any) -> None:
    harness = PluginHarness()
    with Receiver() as receiver:
        dest = harness.start(ingest.Ingest, {"port": receiver.port, "token": TOKEN})
        assert dest.send(BATCH) is None
        assert dest.send(BATCH) is None
        lines = [json.loads(line) for r in receiver.accepted() for line in r.body.decode().splitlines()]
        assert [line["n"] for line in lines] == [0, 1, 2, 0, 1, 2]
        assert {r.header("Authorization") for r in receiver.requests} == {f"Bearer {TOKEN}"}
        assert len({r.client for r in receiver.requests}) == 1, "one kept-alive connection"
        harness.stop(dest)
        assert not dest.connection.is_open


def test_the_example_hands_retry_after_to_the_sender_and_masks_the_token(ingest: Any) -> None:
    def busy(request: Request) -> tuple[int, bytes]:
        return 503, f"overloaded, token {TOKEN}".encode()

    harness = PluginHarness()
    with Receiver(busy) as receiver:
        dest = harness.start(ingest.Ingest, {"port": receiver.port, "token": TOKEN})
        with pytest.raises(RetryableError) as caught:
            dest.send(BATCH)
        assert TOKEN not in str(caught.value) and "HTTP 503" in str(caught.value)
        receiver.respond = lambda request: (400, b"bad batch")
        with pytest.raises(RejectedError, match="HTTP 400"):
            dest.send(BATCH)
        harness.stop(dest)
    with pytest.raises(RetryableError, match=f"cannot POST to http://127.0.0.1:{receiver.port}/ingest"):
        harness.start(ingest.Ingest, {"port": receiver.port}).send(BATCH)


def test_the_example_reads_retry_after(ingest: Any) -> None:
    harness = PluginHarness()
    with RetryAfterServer("7") as server:
        dest = harness.start(ingest.Ingest, {"port": server.port})
        with pytest.raises(RetryableError, match="HTTP 429") as caught:
            dest.send(BATCH)
        assert caught.value.retry_after == 7.0, "the sender's backoff waits it out, not send()"
        harness.stop(dest)


def test_the_example_speaks_verified_tls(ingest: Any, pki: Pki) -> None:
    harness = PluginHarness()
    with Receiver(tls=pki.server_context()) as receiver:
        dest = harness.start(ingest.Ingest, {"port": receiver.port, "tls": True, "tls_ca_file": str(pki.ca)})
        assert dest.send(BATCH) is None
        harness.stop(dest)
        stranger = harness.start(
            ingest.Ingest, {"port": receiver.port, "tls": True, "tls_ca_file": str(pki.stranger_ca)}
        )
        with pytest.raises(RetryableError, match=re.compile("https://127.0.0.1.*certificate", re.IGNORECASE)):
            stranger.send(BATCH)
    assert len(receiver.accepted()) == 1
