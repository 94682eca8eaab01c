"""The tools that talk to running services: echo, hz, status, params, record, replay.

Each is a ``vistrack`` subcommand (``add_arguments(parser)``, ``main(args)``); what they share
(the session, key names, waiting for samples, the status query) is in :mod:`.shared`.
"""
