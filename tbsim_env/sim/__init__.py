"""Batched simulation core: dynamics, geometry, state, collision and off-road checks."""
