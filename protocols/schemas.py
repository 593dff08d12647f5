"""JSON Schemas of every Zenoh payload; the same schemas label the MCAP json channels."""

from __future__ import annotations

import json
from functools import cache
from importlib import resources
from typing import Any

import jsonschema

from protocols.keys import schema_for_key

SCHEMA_NAMES = (
    "telemetry",
    "umodel",
    "command_ballast",
    "setpoint",
    "control",
    "health",
    "decision_inputs",
)

#: The service's own JSON channels beside the Zenoh keys (MCAP only, never published):
#: ``glider-hil/{id}/{kind}`` → schema name.
INTERNAL_SCHEMAS = {"decision-inputs": "decision_inputs"}


@cache
def load_schema(name: str) -> dict[str, Any]:
    if name not in SCHEMA_NAMES:
        raise KeyError(f"no schema {name!r}; known: {SCHEMA_NAMES}")
    text = resources.files("protocols").joinpath("schemas", f"{name}.json").read_text()
    return json.loads(text)


def schema_for_channel(topic: str) -> str | None:
    """The schema name of a recorded JSON channel (a Zenoh key or one of the service's own
    channels), or None when it has none."""
    name = schema_for_key(topic)
    if name is not None:
        return name
    parts = topic.split("/")
    if len(parts) == 3 and parts[0] == "glider-hil" and parts[1].isdigit():
        return INTERNAL_SCHEMAS.get(parts[2])
    return None


@cache
def _validator(name: str) -> jsonschema.protocols.Validator:
    schema = load_schema(name)
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema)


def validation_errors(name: str, payload: Any) -> list[str]:
    """Human-readable reasons ``payload`` does not match schema ``name`` (empty when valid)."""
    return [
        f"{error.json_path}: {error.message}" for error in _validator(name).iter_errors(payload)
    ]


def validate(name: str, payload: Any) -> None:
    """Raise ``ValueError`` naming the first problem when ``payload`` is not valid."""
    errors = validation_errors(name, payload)
    if errors:
        raise ValueError(f"{name} payload invalid: {errors[0]}")
