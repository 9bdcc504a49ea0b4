"""safesysid: provably-safe online identification of robot payloads, on Drake."""

__version__ = "0.1.0"
