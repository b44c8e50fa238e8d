"""The ``mine`` command's top-level verbs, one module each (submit, status, query, label, export,
render, config, view): each offers ``add_arguments(parser)`` and ``run(args)``, like the modules
of ``mine GROUP NAME`` commands, and is imported only when its verb is parsed (``cli.COMMANDS``)."""
