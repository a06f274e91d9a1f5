"""The sim-vs-measured gap workflow: find, name and add the missing effect (offline tool, no node)."""
