"""Terms of a noise model: one module per term, a registry and one model parser.

* :mod:`imunoise.analysis.terms.base`: the :class:`Term` base class and :class:`Param`.
* one module per term (``white``, ``quantization``, ``bias_instability``, ``random_walk``,
  ``rate_ramp``, ``gauss_markov``, ``sinusoid``, ``temperature``), each defining ``TERM``.
* :mod:`imunoise.analysis.terms.registry`: the vocabulary (:data:`TERMS`), found by scanning this
  package, and the Allan variance / PSD of a whole model.
* :mod:`imunoise.analysis.terms.spec`: :func:`parse_model`, the one parser of ``--model`` strings.

See docs/terms.md for the formulas and for how to add a term.
"""

from imunoise.analysis.terms.base import Param, Term, TermError, TermSimulator, param_unit
from imunoise.analysis.terms.bias_instability import BIAS_INSTABILITY_FACTOR
from imunoise.analysis.terms.gauss_markov import ar1_avar_shape
from imunoise.analysis.terms.registry import (
    TERMS,
    _discover,
    get_term,
    model_avar,
    model_psd,
    register,
    term_names,
    validate_params,
)
from imunoise.analysis.terms.spec import (
    Entry,
    ModelSpec,
    labels,
    parse_model,
    parse_terms,
    term_name,
)

_discover()

TERM_NAMES: tuple[str, ...] = term_names()
"""All term names in vocabulary order (derived from the registry)."""

__all__ = ["BIAS_INSTABILITY_FACTOR", "Entry", "ModelSpec", "Param", "TERMS", "TERM_NAMES",
           "Term", "TermError", "TermSimulator", "ar1_avar_shape", "get_term", "labels",
           "model_avar", "model_psd", "param_unit", "parse_model", "parse_terms", "register",
           "term_name", "term_names", "validate_params"]
