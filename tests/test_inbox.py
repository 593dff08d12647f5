"""Control inputs received over Zenoh: validation and the owner's setpoint limits."""

from __future__ import annotations

import json

from hil_service.inputs import MAX_REASON, Inbox, SetpointLimits
from protocols import payload_json


def put(inbox: Inbox, key: str, payload: object) -> None:
    inbox.accept(key, json.dumps(payload).encode())


def test_valid_inputs_are_stored_per_vehicle():
    inbox = Inbox()
    put(inbox, "glider/1/setpoint/depth", {"value": 20.0})
    put(inbox, "glider/2/setpoint/pitch", {"value": -0.1})
    put(inbox, "glider/1/control", {"enabled": True})
    assert inbox.get(1).setpoints == {"depth": 20.0, "pitch": None}
    assert inbox.get(1).enabled is True
    assert inbox.get(2).setpoints == {"depth": None, "pitch": -0.1}
    assert inbox.get(2).enabled is None
    put(inbox, "glider/1/setpoint/depth", {"value": None})  # clears it
    assert inbox.get(1).setpoints["depth"] is None
    assert inbox.rejected == 0
    assert inbox.last_rejection == ""  # health shows last_rejected_input once one is refused
    assert inbox.accept("glider/2/control", b'{"enabled": false}') == ""  # taken: no reason


def test_setpoints_outside_the_limits_are_refused_with_a_reason_not_clipped():
    inbox = Inbox(SetpointLimits(min_depth=2.0, max_depth=100.0, max_abs_pitch=0.4))
    put(inbox, "glider/1/setpoint/depth", {"value": 50.0})
    put(inbox, "glider/1/setpoint/depth", {"value": 150.0})
    assert inbox.get(1).setpoints["depth"] == 50.0, "a refused setpoint must not replace one"
    assert "maximum depth 100 m" in inbox.last_rejection
    put(inbox, "glider/1/setpoint/depth", {"value": 0.5})
    assert "minimum depth 2 m" in inbox.last_rejection
    put(inbox, "glider/1/setpoint/pitch", {"value": -0.5})
    assert "±0.4 rad" in inbox.last_rejection
    assert inbox.get(1).setpoints == {"depth": 50.0, "pitch": None}
    assert inbox.rejected == 3


def test_malformed_inputs_are_counted():
    inbox = Inbox()
    inbox.accept("glider/1/setpoint/depth", b"{not json")
    put(inbox, "glider/1/setpoint/depth", {"value": "deep"})
    put(inbox, "glider/1/setpoint/roll", {"value": 1.0})
    put(inbox, "glider/x/control", {"enabled": True})
    put(inbox, "glider/1/control", {"enabled": "yes"})
    inbox.accept("glider/1/setpoint/depth", b'{"value": NaN}')
    assert inbox.rejected == 6
    assert inbox.get(1).setpoints == {"depth": None, "pitch": None}
    assert inbox.get(1).enabled is None


def test_a_setpoint_never_changes_the_control_flag():
    """Control off stays off when a setpoint arrives (``serve --control`` would otherwise
    fall back to its default, on)."""
    inbox = Inbox()
    put(inbox, "glider/1/control", {"enabled": False})
    put(inbox, "glider/1/setpoint/depth", {"value": 20.0})
    put(inbox, "glider/1/setpoint/pitch", {"value": None})
    assert inbox.get(1).enabled is False
    assert inbox.get(1).setpoints == {"depth": 20.0, "pitch": None}


def test_every_refusal_names_the_key_and_why():
    inbox = Inbox()
    cases = [
        (
            "glider/x/setpoint/depth",
            b'{"value": 1}',
            "glider/x/setpoint/depth: not a setpoint or control key",
        ),
        ("glider/1/setpoint/depth", b"{not json", "glider/1/setpoint/depth: Expecting"),
        ("glider/1/setpoint/depth", b'{"value": "deep"}', "glider/1/setpoint/depth: "),
        ("glider/1/setpoint/depth", b'{"value": NaN}', "glider/1/setpoint/depth: non-finite"),
        ("glider/1/setpoint/roll", b'{"value": 1}', "glider/1/setpoint/roll: not a setpoint or"),
        ("glider/1", b'{"enabled": true}', "glider/1: not a setpoint or control key"),
        ("glider/1/setpoint", b'{"value": 3}', "glider/1/setpoint: not a setpoint or control"),
        ("glider/1/speed", b'{"enabled": true}', "glider/1/speed: not a setpoint or control"),
    ]
    for n, (key, raw, reason) in enumerate(cases, start=1):
        returned = inbox.accept(key, raw)  # what the recorder files the input under
        assert inbox.rejected == n, key
        assert inbox.last_rejection.startswith(reason), (key, inbox.last_rejection)
        assert returned == inbox.last_rejection
    # None of them set anything.
    assert inbox.get(1).enabled is None
    assert inbox.get(1).setpoints == {"depth": None, "pitch": None}


def test_a_setpoint_integer_no_float_holds_is_refused_and_counted():
    inbox = Inbox()  # no limits: the integer check alone stands between it and the log
    for digits in (21, 401):
        reason = inbox.accept("glider/1/setpoint/depth", b'{"value": 1' + b"0" * digits + b"}")
        assert "beyond" in reason
    assert inbox.rejected == 2 and inbox.get(1).setpoints["depth"] is None
    assert inbox.accept("glider/1/setpoint/depth", b'{"value": 20}') == ""
    assert payload_json.encode(inbox.get(1).setpoints)  # what the service logs per decision


def test_json_nested_too_deep_is_refused_and_counted():
    inbox = Inbox()
    reason = inbox.accept("glider/1/setpoint/depth", b"[" * 100_000 + b"]" * 100_000)
    assert "nested too deeply" in reason and inbox.rejected == 1


def test_a_huge_refused_input_leaves_a_short_reason_for_health():
    inbox = Inbox()
    text = "x" * 1_000_000
    reason = inbox.accept("glider/1/setpoint/depth", json.dumps({"value": text}).encode())
    assert len(reason) <= MAX_REASON + 40 and "characters)" in reason
    assert inbox.last_rejection == reason
