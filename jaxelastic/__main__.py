"""``python -m jaxelastic …``: the same as the ``jaxelastic`` command (:mod:`jaxelastic.cli`)."""

from .cli import command

command()
