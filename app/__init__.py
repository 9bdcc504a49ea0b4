"""safesysid: provably-safe online identification of robot payloads, on Drake."""
from pathlib import Path

__version__ = "0.1.0"
