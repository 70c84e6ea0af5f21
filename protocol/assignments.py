"""`NAME=VALUE` lists as typed on command lines (`--weight position=300`,
`--truth-effect stribeck:velocity=0.05`, `dashboard set weights position=300`)."""

from collections.abc import Iterable


def parse_assignments(items: Iterable[str], allowed: Iterable[str] | None,
                      what: str) -> dict[str, float]:
    """{name: float}; ValueError names the item, and the allowed names when there are any."""
    allowed = list(allowed) if allowed is not None else None
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or (allowed is not None and name not in allowed):
            expected = f" with NAME one of {', '.join(allowed)}" if allowed is not None else ""
            raise ValueError(f"{what}: {item!r}: expected NAME=VALUE{expected}")
        try:
            out[name] = float(value)
        except ValueError:
            raise ValueError(f"{what}: {item!r}: {value!r} is not a number") from None
    return out
