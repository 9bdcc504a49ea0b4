"""Timing scripts behind `safesysid bench`."""
