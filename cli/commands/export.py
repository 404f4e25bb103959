"""`cbh export` (being built)."""


def register(app):
    pass
