"""``python -m jaxelastic …``: the same as the ``jaxelastic`` command (:mod:`jaxelastic.cli`)."""

from .cli import command

__all__: list[str] = []

command()
