"""pretest layer (see ARCHITECTURE.md)."""
