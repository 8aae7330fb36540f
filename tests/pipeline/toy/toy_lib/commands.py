"""An extra CLI command for the toy project (``pipeline hello``)."""


def hello(argv: list[str]) -> int:
    print("hello " + " ".join(argv))
    return 3 if "--fail" in argv else 0
