"""``python -m jaxinertia`` runs the command-line tool."""

from jaxinertia.app.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
