"""calibration layer (see ARCHITECTURE.md)."""
