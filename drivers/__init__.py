"""skyfix.drivers (see DESIGN.md); filled in by its issue."""
