"""skyfix.tags (see DESIGN.md); filled in by its issue."""
