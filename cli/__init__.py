"""The `cbh` command line (Typer). Thin: each command parses options and calls cbh."""
