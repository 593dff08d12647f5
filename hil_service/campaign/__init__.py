"""``glider-hil campaign``: many lockstep HIL missions, scored, summarised and compared."""
