"""Where samples come from: one ``SampleSource`` per profile mode (lockstep, periodic)."""
