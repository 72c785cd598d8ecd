"""Stack factories for tests/test_stacks.py: a factory that raises, one that returns no stack."""


def raises():
    raise RuntimeError("no licence server")


def not_a_stack():
    return object()
