"""safesysid."""
