"""In-process experiments on the emulator's plant: identification, closed loop, speed."""
