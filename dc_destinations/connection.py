"""The connection a destination keeps between batches (a socket, an HTTP keep-alive, an MQTT client…).

Opened by the first ``send`` that needs it, in the sender's thread (a server that is down must not
hold up activation); closed after a network error, so that the next attempt starts afresh, and on
deactivate and cleanup once handed to ``Destination.keep``. No lock: the destination server never
runs ``send`` at the same time as ``on_deactivate`` or ``on_cleanup`` (dc_destinations.sender.Gate),
and one thread sends. Its failure texts name the peer, say a timeout in seconds and mask secrets.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable
from typing import Generic, TypeVar

C = TypeVar("C")


class Connection(Generic[C]):
    """``open()`` when needed, ``close(connection)`` when done; ``usable(connection)`` False for one
    found dead (a peer that hung up), which is then closed and opened again.

    ``where`` names the peer in failure texts ("127.0.0.1:5170", a URL without its secrets);
    ``timeout``: the seconds a timed-out operation waited; ``secrets``: masked in every text.
    """

    def __init__(
        self,
        where: str,
        open: Callable[[], C],
        close: Callable[[C], None],
        *,
        timeout: float,
        usable: Callable[[C], bool] | None = None,
        secrets: Iterable[str] = (),
    ) -> None:
        self.where = where
        self.timeout = timeout
        self.secrets = [s for s in secrets if s]
        self._open = open
        self._close = close
        self._usable = usable
        self._current: C | None = None

    @property
    def is_open(self) -> bool:
        return self._current is not None

    def get(self) -> C:
        """The connection, opened (again) when there is none or it is no longer usable."""
        if self._current is not None and self._usable is not None and not self._usable(self._current):
            self.close()
        if self._current is None:
            self._current = self._open()
        return self._current

    def close(self) -> None:
        current, self._current = self._current, None
        if current is not None:
            # A broken connection may fail to close: it is dropped anyway.
            with contextlib.suppress(Exception):
                self._close(current)

    def failure(
        self,
        what: str,
        exc: BaseException,
        *,
        detail: str = "",
        timeout: float | None = None,
        waiting: str = "no answer",
    ) -> str:
        """``"<what> <where>: <detail>"`` with the secrets masked; a timeout said in seconds.

        ``detail``: the reason, when the caller reads it better than ``str(exc)`` (OpenSSL's).
        """
        if isinstance(exc, TimeoutError):
            detail = f"{waiting} within {self.timeout if timeout is None else timeout:g} s"
        return self.scrub(f"{what} {self.where}: {detail or str(exc) or type(exc).__name__}")

    def scrub(self, text: str) -> str:
        return masked(text, self.secrets)


def masked(text: str, secrets: Iterable[str]) -> str:
    """``text`` with every one of ``secrets`` replaced by ``***``, should a server echo a credential back.

    Longest first, so that a secret holding another (a URL and its token) is masked whole.
    """
    for secret in sorted(secrets, key=len, reverse=True):
        if secret:
            text = text.replace(secret, "***")
    return text
