"""``python -m gdt_pipeline.cli``: the same as the ``gdt`` command."""

from . import main

main()
