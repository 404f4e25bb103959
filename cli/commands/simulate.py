"""`cbh simulate` (being built)."""


def register(app):
    pass
