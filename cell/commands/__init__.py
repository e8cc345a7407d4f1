"""Sub-commands of ``cell``: each module defines ``register(app: typer.Typer) -> None``."""
