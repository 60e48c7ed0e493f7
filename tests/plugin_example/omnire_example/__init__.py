"""A third-party plugin as an outside author writes one: it imports the core through
``omnire.api`` only (tests/test_public_api.py checks it with the import contracts of
pyproject.toml and loads it with the real plugin loader)."""
