"""What a profile may choose of the service's do-no-harm behaviour (docs/control.md, "Do no
harm"; the profile's ``[control]`` table, docs/profiles.md)."""

from __future__ import annotations

#: What a channel's input goes to when its supervisor trips: "hold" the input the last
#: clean supervised segment started from, "neutral" (0, the trim), or "release": the
#: service stops commanding the channel (NaN), for a vehicle whose own controller takes
#: the channel back when the service's commands for it stop.
SAFE_INPUTS = ("hold", "neutral", "release")
