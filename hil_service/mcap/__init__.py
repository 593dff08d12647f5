"""MCAP logs: the recorder on the live path, our chunked writer, and the readers."""
