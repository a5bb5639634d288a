"""Built-in stages of gdt-pipeline, one sub-package per family. Each registers through the ``gdt_pipeline``
entry-point group (see pyproject.toml), exactly as a third-party plugin does; the engine never imports them."""
