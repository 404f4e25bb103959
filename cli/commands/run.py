"""`cbh run` (being built)."""


def register(app):
    pass
