"""identification layer (see ARCHITECTURE.md)."""
