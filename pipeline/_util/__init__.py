"""Small helpers every layer may use: the one atomic writer, the one field validator, the
one safe YAML reader."""
