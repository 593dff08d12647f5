"""The live view: a Foxglove WebSocket server streaming the service's channels as it runs."""
