"""The engine. Importing it first asks the thread pools torch and numba are about to load to
wait passively (avatar_core/threads.py): the ``telesplat`` entry point imports this package
before anything imports torch."""

from .threads import passive_waiting as _passive_waiting

_passive_waiting()
