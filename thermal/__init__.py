"""skyfix.thermal (see DESIGN.md); filled in by its issue."""
