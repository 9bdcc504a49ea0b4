"""Task role of safesysid.systems (see docs/design.md)."""
