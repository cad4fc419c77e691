from jaxinertia.app.cli import main  # noqa: F401  interim: removed when the redesign lands
