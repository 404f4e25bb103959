"""`cbh replay` (being built)."""


def register(app):
    pass
