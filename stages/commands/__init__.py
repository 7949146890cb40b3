"""The ``cobgs`` command line: the commands that are not stages.

They sit above every layer (they drive the library, the engine, the stages and the
report builder), so they live apart from the stage files: ``cli`` builds the parser from
the providers here, each exposing ``register(subparsers)``.
"""
