"""skyfix.crps (see DESIGN.md); filled in by its issue."""
