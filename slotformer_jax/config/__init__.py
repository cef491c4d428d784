"""The run configuration: `defaults.py` (every field with its meaning, and the
recipes dataset configs share) and `checks.py` (every check a config can fail,
run before any work)."""
