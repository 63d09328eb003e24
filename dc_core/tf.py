"""DC's own TF buffer: coordinate-frame transforms kept over time, looked up through chains of frames.

tf2_ros is not on PyPI, so DC (which runs from a plain venv) cannot use its ``Buffer``. This module is the
part DC needs of it, in pure Python and without any ROS import: a tree of frames (each child has one parent),
static links that hold at every time, dynamic links kept for ``cache_s`` seconds and interpolated between
samples, and ``lookup(target, source, time)`` with the meaning of tf2's ``lookupTransform``. Feeding it from
/tf and /tf_static is another module's job.
"""

from __future__ import annotations

import bisect
import math
import threading
from dataclasses import dataclass, field

Vector = tuple[float, float, float]
Quaternion = tuple[float, float, float, float]

# Below this angle between two rotations slerp divides by ~0: normalised lerp is as exact there.
_NLERP_DOT = 0.9995


def _normalised(q: Quaternion) -> Quaternion:
    norm = math.sqrt(sum(c * c for c in q))
    if norm == 0.0:
        return (0.0, 0.0, 0.0, 1.0)
    return (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)


def _multiply(a: Quaternion, b: Quaternion) -> Quaternion:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def _rotate(q: Quaternion, v: Vector) -> Vector:
    x, y, z, w = _normalised(q)
    # v' = v + 2w (u x v) + 2 u x (u x v), u = (x, y, z): no matrix needed.
    cx, cy, cz = y * v[2] - z * v[1], z * v[0] - x * v[2], x * v[1] - y * v[0]
    ccx, ccy, ccz = y * cz - z * cy, z * cx - x * cz, x * cy - y * cx
    return (v[0] + 2 * (w * cx + ccx), v[1] + 2 * (w * cy + ccy), v[2] + 2 * (w * cz + ccz))


def quaternion_from_yaw(yaw: float) -> Quaternion:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


@dataclass(frozen=True)
class Transform:
    """Pose of a child frame in its parent frame: maps points given in the child frame into the parent frame."""

    translation: Vector = (0.0, 0.0, 0.0)
    rotation: Quaternion = (0.0, 0.0, 0.0, 1.0)  # x, y, z, w

    def compose(self, other: Transform) -> Transform:
        """``T_a_c = T_a_b.compose(T_b_c)``: applying the result equals ``self.apply(other.apply(p))``."""
        return Transform(self.apply(other.translation), _normalised(_multiply(self.rotation, other.rotation)))

    def inverse(self) -> Transform:
        x, y, z, w = _normalised(self.rotation)
        conjugate = (-x, -y, -z, w)
        tx, ty, tz = _rotate(conjugate, self.translation)
        return Transform((-tx, -ty, -tz), conjugate)

    def apply(self, point: Vector) -> Vector:
        rx, ry, rz = _rotate(self.rotation, point)
        tx, ty, tz = self.translation
        return (rx + tx, ry + ty, rz + tz)

    @property
    def yaw(self) -> float:
        """Rotation about z (ZYX convention) in (-pi, pi]."""
        x, y, z, w = self.rotation
        angle = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        return math.pi if angle == -math.pi else angle

    @staticmethod
    def from_xy_yaw(x: float, y: float, yaw: float) -> Transform:
        return Transform((x, y, 0.0), quaternion_from_yaw(yaw))


def interpolate(a: Transform, b: Transform, fraction: float) -> Transform:
    """Linear translation, slerp rotation along the shortest path; fraction 0 -> a, 1 -> b."""
    translation = (
        a.translation[0] + (b.translation[0] - a.translation[0]) * fraction,
        a.translation[1] + (b.translation[1] - a.translation[1]) * fraction,
        a.translation[2] + (b.translation[2] - a.translation[2]) * fraction,
    )
    qa, qb = _normalised(a.rotation), _normalised(b.rotation)
    dot = sum(ca * cb for ca, cb in zip(qa, qb, strict=True))
    if dot < 0.0:
        # q and -q are the same rotation; the other sign would go the long way round.
        qb, dot = (-qb[0], -qb[1], -qb[2], -qb[3]), -dot
    if dot > _NLERP_DOT:
        wa, wb = 1.0 - fraction, fraction
    else:
        theta = math.acos(dot)
        wa, wb = math.sin((1.0 - fraction) * theta) / math.sin(theta), math.sin(fraction * theta) / math.sin(theta)
    rotation = _normalised(
        (wa * qa[0] + wb * qb[0], wa * qa[1] + wb * qb[1], wa * qa[2] + wb * qb[2], wa * qa[3] + wb * qb[3])
    )
    return Transform(translation, rotation)


class TransformError(Exception):
    """A lookup that cannot be answered; str() is the reason for a user."""


def _seconds(ns: int) -> str:
    return f"{ns / 1e9:.6f}".rstrip("0").rstrip(".")


def _frame(name: str) -> str:
    return name.removeprefix("/")


@dataclass
class _Link:
    """How one child frame hangs from its parent: a static transform, or samples sorted by stamp."""

    parent: str
    static: Transform | None = None
    stamps: list[int] = field(default_factory=list)
    transforms: list[Transform] = field(default_factory=list)

    def at(self, child: str, time_ns: int, tolerance_ns: int) -> Transform:
        if self.static is not None:
            return self.static
        name = f"{self.parent} -> {child}"
        if time_ns > self.stamps[-1]:
            late = time_ns - self.stamps[-1]
            if late > tolerance_ns:
                raise TransformError(
                    f"extrapolation into the future: requested time {_seconds(time_ns)} s is {_seconds(late)} s "
                    f"after the newest transform {name} (at {_seconds(self.stamps[-1])} s)"
                )
            return self.transforms[-1]
        if time_ns < self.stamps[0]:
            early = self.stamps[0] - time_ns
            if early > tolerance_ns:
                raise TransformError(
                    f"extrapolation into the past: requested time {_seconds(time_ns)} s is {_seconds(early)} s "
                    f"before the oldest transform {name} (at {_seconds(self.stamps[0])} s)"
                )
            return self.transforms[0]
        i = bisect.bisect_left(self.stamps, time_ns)
        if self.stamps[i] == time_ns:
            return self.transforms[i]
        before, after = self.stamps[i - 1], self.stamps[i]
        return interpolate(self.transforms[i - 1], self.transforms[i], (time_ns - before) / (after - before))


class TransformBuffer:
    """Frames and their links over time; safe to feed from one thread and query from another.

    Each child frame has one link to one parent. A static transform for a child replaces whatever link it had;
    so does a dynamic sample with another parent that is newer than the link's samples (older ones are dropped:
    the most recent sample decides the parent, and samples relative to two parents cannot be interpolated).
    """

    def __init__(self, cache_s: float = 10.0) -> None:
        self._cache_ns = int(cache_s * 1e9)
        self._links: dict[str, _Link] = {}
        self._lock = threading.Lock()

    def set_transform(
        self, parent: str, child: str, stamp_ns: int, transform: Transform, *, static: bool = False
    ) -> bool:
        """Record the pose of ``child`` in ``parent`` at ``stamp_ns``; ValueError when parent == child or empty.

        False when the sample was ignored: more than ``cache_s`` older than the link's newest sample, or
        older than the newest sample of the link from another parent.
        """
        parent, child = _frame(parent), _frame(child)
        if not parent or not child or parent == child:
            raise ValueError(f"invalid transform {parent!r} -> {child!r}: frames must be distinct and non-empty")
        with self._lock:
            link = self._links.get(child)
            if static:
                self._links[child] = _Link(parent, static=transform)
                return True
            if link is None or link.static is not None or (link.parent != parent and stamp_ns > link.stamps[-1]):
                self._links[child] = _Link(parent, stamps=[stamp_ns], transforms=[transform])
                return True
            if link.parent != parent or stamp_ns < link.stamps[-1] - self._cache_ns:
                return False
            i = bisect.bisect_left(link.stamps, stamp_ns)
            if i < len(link.stamps) and link.stamps[i] == stamp_ns:
                link.transforms[i] = transform
                return True
            link.stamps.insert(i, stamp_ns)
            link.transforms.insert(i, transform)
            drop = bisect.bisect_left(link.stamps, link.stamps[-1] - self._cache_ns)
            del link.stamps[:drop], link.transforms[:drop]
            return True

    def lookup(self, target_frame: str, source_frame: str, time_ns: int = 0, *, tolerance_ns: int = 0) -> Transform:
        """The pose of ``source_frame`` in ``target_frame`` at ``time_ns`` (maps source points into target).

        ``time_ns == 0`` is the latest time at which every dynamic link of the chain is known. A frame looked up
        in itself is the identity, even when the frame is unknown (unlike tf2).
        """
        with self._lock:
            return self._lookup(_frame(target_frame), _frame(source_frame), time_ns, tolerance_ns)

    def can_transform(
        self, target_frame: str, source_frame: str, time_ns: int = 0, *, tolerance_ns: int = 0
    ) -> str | None:
        """None when lookup would succeed, else the reason it would fail."""
        try:
            self.lookup(target_frame, source_frame, time_ns, tolerance_ns=tolerance_ns)
        except TransformError as error:
            return str(error)
        return None

    def latest_time(self, target_frame: str, source_frame: str) -> int:
        """The time ``lookup(target, source, 0)`` uses; 0 when the chain is all static (or target == source)."""
        target, source = _frame(target_frame), _frame(source_frame)
        with self._lock:
            if target == source:
                return 0
            return self._latest(self._chain(target, source))

    def frames(self) -> set[str]:
        with self._lock:
            return set(self._links) | {link.parent for link in self._links.values()}

    def clear(self) -> None:
        """Forget dynamic samples (the clock jumped backwards: a bag restarted); static transforms stay."""
        with self._lock:
            self._links = {child: link for child, link in self._links.items() if link.static is not None}

    def _lookup(self, target: str, source: str, time_ns: int, tolerance_ns: int) -> Transform:
        if target == source:
            return Transform()
        up_source, up_target = self._chain(target, source)
        if time_ns == 0:
            time_ns = self._latest((up_source, up_target))
        try:
            common_source = self._compose(up_source, time_ns, tolerance_ns)
            common_target = self._compose(up_target, time_ns, tolerance_ns)
        except TransformError as error:
            raise TransformError(f"no transform from {target!r} to {source!r}: {error}") from None
        return common_target.inverse().compose(common_source)

    def _chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """The frames below the common ancestor on the way up from source and from target."""
        known = self._links.keys() | {link.parent for link in self._links.values()}
        for name in (target, source):
            if name not in known:
                raise TransformError(f"no transform from {target!r} to {source!r}: frame {name!r} is unknown")
        source_path, target_path = self._to_root(target, source, source), self._to_root(target, source, target)
        if source_path[-1] != target_path[-1]:
            raise TransformError(
                f"no transform from {target!r} to {source!r}: {target!r} and {source!r} are not connected "
                f"(trees rooted at {target_path[-1]!r} and {source_path[-1]!r})"
            )
        # Both paths end at the root; strip their shared tail to stop at the common ancestor.
        while len(source_path) > 1 and len(target_path) > 1 and source_path[-2] == target_path[-2]:
            source_path.pop()
            target_path.pop()
        return source_path[:-1], target_path[:-1]

    def _to_root(self, target: str, source: str, frame: str) -> list[str]:
        path = [frame]
        while (link := self._links.get(path[-1])) is not None:
            if link.parent in path:
                raise TransformError(
                    f"no transform from {target!r} to {source!r}: the parent links of {frame!r} form a loop "
                    f"({' -> '.join([*path, link.parent])})"
                )
            path.append(link.parent)
        return path

    def _latest(self, chains: tuple[list[str], list[str]]) -> int:
        links = [self._links[child] for child in chains[0] + chains[1]]
        return min((link.stamps[-1] for link in links if link.static is None), default=0)

    def _compose(self, path: list[str], time_ns: int, tolerance_ns: int) -> Transform:
        """The pose of path[0] in the parent of path[-1]."""
        result = Transform()
        for child in path:
            result = self._links[child].at(child, time_ns, tolerance_ns).compose(result)
        return result
