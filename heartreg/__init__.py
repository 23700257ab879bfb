"""heartreg: beating-heart registration for organ-mounted robots.

The application package: the command line (:mod:`heartreg.cli`), the end-to-end
pipeline and the synthetic beating-heart phantom (:mod:`heartreg.phantom`).
The library stages live in the sibling packages ``imaging``, ``modeling`` and
``registration``.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
