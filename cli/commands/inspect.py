"""`cbh inspect` (being built)."""


def register(app):
    pass
