"""Writes a copy of an MCAP log that Foxglove Studio 1.48 can plot.

Studio 1.48 derives a JSON channel's fields from its JSON Schema and knows only part of the
language: no type lists (our nullable fields, ``["number", "null"]``), no maps (an object with
``additionalProperties`` and no ``properties``, like ``health.identifier``) and no field the
schema does not declare. Our schemas (protocols/schemas/, docs/mcap.md) use all three, so
Studio drops those channels ("Unsupported type ["number","null"] for ...").

The copy keeps every JSON channel's topic, encoding, schema name and every message byte for
byte with its times; only the schema's text is rewritten for Studio: a type list becomes
its non-null type, and an object's fields are those its schema declares plus the keys its
messages carry (a map's keys, undeclared fields), typed by the schema where it says and by
the values where it does not. Channels Studio cannot decode at all (raw ``mavlink2``
frames, no schema) are left out. The copy is a viewing aid, never a log to replay.

Run: .venv/bin/python tools/foxglove_studio/compat_log.py LOG.mcap -o COPY.mcap
(prints the copy's channels, then ``end TIME``: its last message's log time, RFC 3339).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

SCALARS = {"boolean", "string", "number", "integer"}


def _value_type(value: Any) -> str | None:
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, (int, float)):
        return "number"
    if isinstance(value, str):
        return "string"
    if isinstance(value, dict):
        return "object"
    if isinstance(value, list):
        return "array"
    return None


def _declared_type(schema: dict[str, Any]) -> str | None:
    declared = schema.get("type")
    if isinstance(declared, list):
        declared = next((t for t in declared if t != "null"), None)
    return declared if isinstance(declared, str) else None


def studio_schema(schema: dict[str, Any], samples: list[Any]) -> dict[str, Any] | None:
    """The part of ``schema`` Studio 1.48 reads, completed from ``samples`` (the values at
    this place in the channel's messages). None when nothing says what the field is (only
    nulls seen and no type declared, or an array of arrays)."""
    present = [s for s in samples if s is not None]
    kind = _declared_type(schema)
    if kind is None:
        kinds = {_value_type(s) for s in present} - {None}
        kind = kinds.pop() if len(kinds) == 1 else None
    if kind in SCALARS:
        return {"type": "number" if kind == "integer" else kind}
    if kind == "object":
        declared = schema.get("properties") or {}
        extra = schema.get("additionalProperties")
        extra_schema = extra if isinstance(extra, dict) else {}
        keys = list(declared)
        for sample in present:
            if isinstance(sample, dict):
                keys += [k for k in sample if k not in keys]
        properties = {}
        for key in keys:
            sub = studio_schema(
                declared.get(key, extra_schema),
                [s.get(key) for s in present if isinstance(s, dict)],
            )
            if sub is not None:
                properties[key] = sub
        return {"type": "object", "properties": properties}
    if kind == "array":
        items = schema.get("items") if isinstance(schema.get("items"), dict) else {}
        elements = [e for s in present if isinstance(s, list) for e in s]
        item = studio_schema(items, elements)
        if item is None or item["type"] == "array":
            return None
        return {"type": "array", "items": item}
    return None


def convert(src: Path, dst: Path) -> dict[str, int]:
    """Writes the copy; returns how many channels were kept and left out, and the log time
    of the last message (ns)."""
    with src.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        if summary is None:
            raise ValueError(f"{src}: no summary section (an unfinished log?)")
        payloads: dict[int, list[Any]] = defaultdict(list)
        for _, channel, message in reader.iter_messages():
            if channel.message_encoding == "json":
                payloads[channel.id].append(json.loads(message.data))
    kept = {
        cid: ch
        for cid, ch in summary.channels.items()
        if ch.message_encoding == "json" and ch.schema_id in summary.schemas
    }
    left_out = len(summary.channels) - len(kept)
    with src.open("rb") as f, dst.open("wb") as out:
        writer = Writer(out, compression=CompressionType.NONE)
        writer.start(profile="", library="glider-hil tools/foxglove_studio/compat_log.py")
        ids: dict[int, int] = {}
        for cid, ch in sorted(kept.items()):
            schema = summary.schemas[ch.schema_id]
            rewritten = studio_schema(json.loads(schema.data), payloads[cid]) or {
                "type": "object",
                "properties": {},
            }
            schema_id = writer.register_schema(
                name=schema.name, encoding="jsonschema", data=json.dumps(rewritten).encode()
            )
            ids[cid] = writer.register_channel(
                topic=ch.topic,
                message_encoding="json",
                schema_id=schema_id,
                metadata=dict(ch.metadata),
            )
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if channel.id in ids:
                writer.add_message(
                    channel_id=ids[channel.id],
                    log_time=message.log_time,
                    publish_time=message.publish_time,
                    sequence=message.sequence,
                    data=message.data,
                )
        writer.finish()
    end = summary.statistics.message_end_time if summary.statistics else 0
    return {"kept": len(kept), "left_out": left_out, "end_ns": end}


def rfc3339(ns: int) -> str:
    """UTC, nanoseconds: Studio's ``?time=`` deep-link parameter."""
    seconds, frac = divmod(ns, 1_000_000_000)
    stamp = datetime.fromtimestamp(seconds, tz=timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")
    return f"{stamp}.{frac:09d}Z"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("-o", "--out", type=Path, required=True)
    args = parser.parse_args()
    counts = convert(args.log, args.out)
    print(f"{args.out}: {counts['kept']} JSON channels, {counts['left_out']} left out")
    print(f"end {rfc3339(counts['end_ns'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
