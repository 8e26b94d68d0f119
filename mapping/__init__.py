"""skyfix.mapping (see DESIGN.md); filled in by its issue."""
