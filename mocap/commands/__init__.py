"""Command-line sub-commands: each module wires arguments to one stage."""
