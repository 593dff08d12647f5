"""``glider-hil campaign``: many lockstep HIL missions, scored, summarised and compared."""

#: Mission scenarios: the emulator's glider scenarios, and ``random`` (one vehicle of the
#: seed's random plant family, ``plant_emulator.random_plants``). Here, not in ``mission``,
#: so that the verb's parser is built without importing the numerics.
SCENARIOS = ("paper", "disturbed", "nonlinear", "random")
