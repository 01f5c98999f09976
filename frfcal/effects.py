"""Undeclared effects for synthetic truth data: what the test article has and the calibration model lacks.

An :class:`Effect` is one physical addition to a deck, expressed as a term of
femodel's term families (:class:`femodel.AddedSpring`,
:class:`femodel.AddedMass`, :class:`femodel.ElementFactor`) at a physical
value, on some or all articles of a synthetic campaign
(:func:`frfcal.synth.synthesize`). The truth of an article is the deck's
parametric model extended by the terms of its effects
(:meth:`femodel.ParametricModel.with_terms`); the calibration model is the deck
without them.

The effects are defined by the physical truth (a spring between two named
facing grids, a mass on named grids, a factor on named elements), never by a
candidate generator of the diagnosis path under test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class EffectError(ValueError):
    """An invalid effect (the message names the effect and the field at fault)."""


@dataclass(frozen=True)
class Effect:
    """One undeclared physical effect of the test articles.

    Parameters
    ----------
    term : femodel.AddedSpring, femodel.AddedMass or femodel.ElementFactor
        Where and how the effect acts (its ``scale`` and bounds only matter to
        a calibration that would fit it; here the ``value`` is imposed).
    value : float
        Physical value, SI: spring rate (N/m or N m/rad, > 0), mass (kg,
        > 0), or the factor 1 + p of an element subset (> 0, != 1).
    articles : sequence of int or str, optional
        Article indices (0-based) or names that have the effect; None = all.
    family : str, optional
        A label of the physical family (e.g. ``"contact_spring"``); default
        the term's class name.
    """

    term: object
    value: float
    articles: tuple | None = None
    family: str = ""

    def __post_init__(self) -> None:
        from femodel._terms import TERM_FAMILIES, ElementFactor

        if not isinstance(self.term, TERM_FAMILIES):
            raise EffectError(f"Effect: term must be one of {', '.join(c.__name__ for c in TERM_FAMILIES)}, "
                              f"got {type(self.term).__name__}")
        v = float(self.value)
        name = self.term.name
        if not np.isfinite(v) or v <= 0.0:
            raise EffectError(f"Effect {name!r}: value must be positive and finite, got {self.value!r}")
        if isinstance(self.term, ElementFactor) and v == 1.0:
            raise EffectError(f"Effect {name!r}: a factor of exactly 1 changes nothing")
        object.__setattr__(self, "value", v)
        if self.articles is not None:
            arts = tuple(a if isinstance(a, str) else int(a) for a in self.articles)
            if not arts:
                raise EffectError(f"Effect {name!r}: articles must be None (all) or a non-empty list")
            object.__setattr__(self, "articles", arts)
        if not self.family:
            object.__setattr__(self, "family", type(self.term).__name__)

    @property
    def name(self) -> str:
        return self.term.name

    @property
    def p(self) -> float:
        """The term's normalized parameter at ``value``."""
        return float(self.term.normalized(self.value))

    @property
    def unit(self) -> str:
        return self.term.unit or "factor"

    def applies_to(self, index: int, name: str) -> bool:
        """Whether the article with 0-based ``index`` and ``name`` has the effect."""
        return self.articles is None or index in self.articles or name in self.articles

    def record(self, articles) -> dict:
        """JSON-able description: family, term, name, value, unit, where it acts, description, articles.

        Parameters
        ----------
        articles : sequence of str
            The campaign's article names (the record lists those that have it).
        """
        from femodel._terms import AddedMass, AddedSpring

        t = self.term
        out = {"family": self.family, "term": type(t).__name__, "name": t.name, "value": self.value,
               "unit": self.unit, "description": t.description}
        if isinstance(t, AddedSpring):
            out["dofs"] = [list(d) for d in t.dofs]
            out["grids"] = sorted({g for d in t.dofs for g in (d[0], d[2]) if g})
        elif isinstance(t, AddedMass):
            out["grids"] = list(t.grids)
        else:
            out["elements"] = list(t.elements)
            out["kind"] = t.kind
        out["articles"] = [a for i, a in enumerate(articles) if self.applies_to(i, a)]
        return out


def resolve_articles(effects, articles) -> list[tuple[int, ...]]:
    """Per article (in order), the indices into ``effects`` of the effects it has.

    Raises :class:`EffectError` for an article index or name not in ``articles``
    or two effects with the same term name.
    """
    effects = tuple(effects)
    names = [e.name for e in effects]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise EffectError(f"effects: term name(s) {dup} used twice")
    for e in effects:
        if not isinstance(e, Effect):
            raise EffectError(f"effects: expected Effect entries, got {type(e).__name__}")
        for a in e.articles or ():
            if (isinstance(a, str) and a not in articles) or (isinstance(a, int) and not 0 <= a < len(articles)):
                raise EffectError(f"Effect {e.name!r}: article {a!r} is not one of {list(articles)}")
    return [tuple(k for k, e in enumerate(effects) if e.applies_to(i, a)) for i, a in enumerate(articles)]
