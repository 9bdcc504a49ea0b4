"""The hardware boundary: the arm reached over LCM on Drake's own lcmtypes (docs/hardware.md)."""
