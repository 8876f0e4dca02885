"""calfit: identification of calf soft-tissue properties from MRI under compression.

The package drives the finite-element engine ``calfit-fe`` (built from
``solver_cpp/`` and installed in ``orchestrator/bin``) one input deck at a time.
"""

__version__ = "0.1.0"
