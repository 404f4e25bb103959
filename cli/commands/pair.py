"""`cbh pair` (being built)."""


def register(app):
    pass
