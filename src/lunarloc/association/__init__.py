"""Data association: putative pairs, sparse consistency graphs, densest-clique solvers."""

from lunarloc.association.clique import max_clique
from lunarloc.association.clipper import clipper_clique
from lunarloc.association.putative import putative_associations

__all__ = ["max_clique", "clipper_clique", "putative_associations"]
