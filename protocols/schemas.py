"""JSON Schemas of every Zenoh payload; the same schemas label the MCAP json channels."""

from __future__ import annotations

import json
from functools import cache
from importlib import resources
from typing import Any

import jsonschema

SCHEMA_NAMES = (
    "telemetry",
    "umodel",
    "command_ballast",
    "setpoint",
    "control",
    "health",
    "supervisor_event",
    "decision_inputs",
    "rejected_input",
)


@cache
def load_schema(name: str) -> dict[str, Any]:
    if name not in SCHEMA_NAMES:
        raise KeyError(f"no schema {name!r}; known: {SCHEMA_NAMES}")
    text = resources.files("protocols").joinpath("schemas", f"{name}.json").read_text()
    return json.loads(text)


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
