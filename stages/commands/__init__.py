"""The ``cobgs`` command line: the commands that are not stages.

They sit above every layer (they drive the library, the engine, the stages and the
report builder), so they live apart from the stage files: ``cli`` builds the parser from
the providers here, each exposing ``register(subparsers)``.
"""


#: Most frames of one orbit GIF: one per degree (each frame is a CPU render of the object and of
#: the scene without it, ~0.1-1 s apiece, and up to 256 KiB in the GIF).
MAX_FRAMES = 360


def frame_count(text: str) -> int:
    """argparse type of ``--turntables N``: a whole number of frames, 0 (none) to
    :data:`MAX_FRAMES`."""
    import argparse

    try:
        n = int(text)
    except ValueError:
        n = -1
    if not 0 <= n <= MAX_FRAMES:
        raise argparse.ArgumentTypeError(f"expected a number of frames from 0 (none) to {MAX_FRAMES} (one per "
                                         f"degree; each is two CPU renders per object), got {text!r}")
    return n
