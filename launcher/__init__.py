"""launcher"""

# One BLAS thread in every shapefleet process, whichever package a script imports first: the setting
# and why live in agents/__init__.py.
import agents  # noqa: F401
