"""skyfix.fusion (see DESIGN.md); filled in by its issue."""
