"""Sub-commands of ``eigencast``; each module: HELP, add_arguments(parser), run(args)."""
