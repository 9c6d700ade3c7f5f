"""WOSAC realism metrics (2024 and 2025 sim-agents challenges), vectorised in torch."""
