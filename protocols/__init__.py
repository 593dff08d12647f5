"""MAVLink mapping, Zenoh key space and JSON Schemas of glider-hil."""

from protocols.compiled import apply_choice

apply_choice()  # GLIDER_HIL_INTERPRETED=1: run the Python sources of the compiled modules
