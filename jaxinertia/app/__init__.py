"""The application layer: the command line, the paper's pipeline, reports and plots.

Everything here sits above the library (:mod:`jaxinertia` and its subpackages) and may
import any of it; nothing in the library imports from here.
"""
