"""Hostile input for the servers' intakes, mixed with numbered valid records (fuzz tests).

Every text says by construction what a server must do with it: count it as malformed, or carry
it as the valid record it is (odd as it looks). A valid record carries ``n`` (the numbered ones)
or ``odd`` (the odd valid ones), so a test can check that each arrived exactly once.
"""

from __future__ import annotations

import json
import random
from dataclasses import dataclass


@dataclass(frozen=True)
class Input:
    text: str
    kind: str
    malformed: bool  # True: must be counted as malformed; False: a valid record that must arrive
    n: int | None = None  # numbered valid record
    odd: int | None = None  # odd but valid record


def _random_text(rng: random.Random) -> str:
    # Printable and not: control characters, non-ASCII, braces and quotes; never a surrogate (a
    # Python string holding one cannot even be published). "x" first: it can never be a JSON object.
    alphabet = '{}[]":,\\ \t\n\x00\x01\x7feé€😀0123456789-+.eE' + "abcdefnulltrue"
    return "x" + "".join(rng.choice(alphabet) for _ in range(rng.randint(0, 300)))


def _malformed(rng: random.Random, tags: list[str]) -> tuple[str, str]:
    tag_text = json.dumps(tags)
    choice = rng.randrange(9)
    if choice == 0:
        return "random-text", _random_text(rng)
    if choice == 1:
        half = rng.choice(["\\ud800", "\\udbff", "\\udc00", "\\udcff", "\\udfff"])
        return "lone-surrogate", f'{{"t": "a{half}b", "tags": {tag_text}}}'
    if choice == 2:
        depth = rng.randint(1_500, 20_000)
        return "deep", f'{{"a": {"[" * depth}{"]" * depth}, "tags": {tag_text}}}'
    if choice == 3:
        value = rng.choice(["NaN", "Infinity", "-Infinity", "1e999", "-2E+400"])
        return "non-finite", f'{{"v": {value}, "tags": {tag_text}}}'
    if choice == 4:
        return "not-an-object", rng.choice(["[1, 2]", '"text"', "null", "42", "true", "[]", '[{"tags": []}]'])
    if choice == 5:
        valid = json.dumps({"v": rng.random(), "s": "é" * rng.randint(0, 5), "tags": tags})
        return "truncated", valid[: rng.randrange(len(valid))]
    if choice == 6:
        return "huge-integer", f'{{"v": {"9" * rng.randint(5_000, 8_000)}, "tags": {tag_text}}}'
    if choice == 7:
        return "empty", rng.choice(["", " ", "\n"])
    return "two-objects", f'{{"tags": {tag_text}}} {{"tags": {tag_text}}}'


def _odd_valid(rng: random.Random, tags: list[str], odd: int) -> tuple[str, str]:
    tag_text = json.dumps(tags)
    choice = rng.randrange(5)
    if choice == 0:
        return "duplicate-keys", f'{{"odd": -1, "odd": {odd}, "tags": ["nowhere"], "tags": {tag_text}}}'
    if choice == 1:
        # DC's own key names, set by a publisher: DC's values win where DC writes them.
        return "dc-keys", json.dumps({"odd": odd, "record_id": "forged", "date": "forged", "tags": tags})
    if choice == 2:
        # A surrogate pair (one character, valid), a NUL, control characters.
        return "escapes", f'{{"odd": {odd}, "t": "\\ud83d\\ude00\\u0000\\u001f\\n\\"", "tags": {tag_text}}}'
    if choice == 3:
        return "huge-string", json.dumps({"odd": odd, "s": "é" * rng.randint(20_000, 100_000), "tags": tags})
    return "nested", json.dumps({"odd": odd, "a": _nest(rng.randint(1, 50)), "tags": tags})


def _nest(depth: int) -> object:
    value: object = {"leaf": True}
    for i in range(depth):
        value = [value] if i % 2 else {"k": value}
    return value


def hostile_stream(valid: int, hostile: int, tags: list[str], seed: int) -> list[Input]:
    """``valid`` numbered records (n = 0, 1, ...) with ``hostile`` others between them, shuffled in.

    About one hostile input in ten is odd but valid; the rest must be counted as malformed.
    """
    rng = random.Random(seed)
    numbered = [Input(json.dumps({"n": n, "tags": tags}), "numbered", False, n=n) for n in range(valid)]
    others: list[Input] = []
    odd = 0
    for _ in range(hostile):
        if rng.random() < 0.1:
            kind, text = _odd_valid(rng, tags, odd)
            others.append(Input(text, kind, False, odd=odd))
            odd += 1
        else:
            kind, text = _malformed(rng, tags)
            others.append(Input(text, kind, True))
    # Shuffle the hostile ones in while the numbered ones keep their order.
    stream: list[Input] = []
    slots = sorted(rng.randrange(valid + 1) for _ in others)
    position = 0
    for n, record in enumerate(numbered):
        while position < len(slots) and slots[position] == n:
            stream.append(others[position])
            position += 1
        stream.append(record)
    stream.extend(others[position:])
    return stream
