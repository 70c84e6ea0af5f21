"""Model TOML writing: the files `identify` and `model-gap` produce. The reading side, with
validation, is `model.parameters.load_model`."""

import os
from dataclasses import fields
from pathlib import Path

import tomli_w

from model.parameters import ActuatorModel, ActuatorParameters


def write_model(path: Path, parameters: ActuatorParameters, like: ActuatorModel, name: str,
                provenance: dict[str, str], std: dict[str, float] | None = None) -> None:
    """Write `parameters` as a model file; limits (and their provenance) come from `like`,
    every parameter's provenance from `provenance` (falling back to `like`'s), and each
    enabled effect gets its own [effects.NAME] table."""
    names = [f.name for f in fields(ActuatorParameters) if f.name != "effects"]
    doc = {
        "meta": {"name": name},
        "parameters": {n: float(getattr(parameters, n)) for n in names},
        "provenance": {n: provenance.get(n, like.provenance.get(n, "unknown")) for n in names},
    }
    if std:
        doc["std"] = {n: float(v) for n, v in std.items()}
    doc["limits"] = vars(like.limits)
    doc["limits_provenance"] = {k.removeprefix("limits."): v for k, v in like.provenance.items()
                                if k.startswith("limits.")}
    effects = {}
    for effect in parameters.effects.enabled():
        key = f"effects.{effect}"
        effects[effect] = {**parameters.effects.section(effect),
                           "provenance": provenance.get(key, like.provenance.get(key, ""))}
    if effects:
        doc["effects"] = effects
    write_atomically(path, tomli_w.dumps(doc).encode())


def write_atomically(path: Path, data: bytes) -> None:
    """`data` as the file `path`, whole or not at all: written beside it and renamed over it,
    so a full disk or a crash leaves no half-written file (and an older file intact). Raises
    OSError."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.writing")
    try:
        with open(temporary, "xb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
