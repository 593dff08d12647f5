"""The glider-hil service: identification, inverse control, Zenoh, MCAP."""

import protocols  # noqa: F401 - applies the compiled/interpreted choice (protocols.compiled)
