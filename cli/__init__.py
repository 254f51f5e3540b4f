"""The ``posefuse`` command line: one module per group of commands, each with a ``register``
function that adds its sub-commands; more groups come from the ``posefuse.commands`` entry
points (see :mod:`cli.main`)."""
