"""The ``cobgs`` command line: the commands that are not stages.

They sit above every layer (they drive the library, the engine, the stages and the
report builder), so they live apart from the stage files: ``cli`` builds the parser from
the providers here, each exposing ``register(subparsers)``.
"""


def frame_count(text: str) -> int:
    """argparse type of ``--turntables N``: a whole number of frames, 0 (none) or more."""
    import argparse

    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"expected a number of frames >= 0 (0 = none), got {text!r}")
    return n
