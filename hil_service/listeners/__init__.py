"""Everything that consumes the service's stream, behind one fan-out."""
