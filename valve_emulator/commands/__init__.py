"""Sub-commands of ``valve-emulator`` (layer 5): each module has NAME, HELP, add_arguments, run."""
