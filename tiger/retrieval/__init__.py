"""Text -> 3D Gaussians: relevance scores, selection, object bounds and 2D relevancy maps."""
from __future__ import annotations

from .guard import SelectionCheck, check_selection
from .maps import (relevancy_maps, render_language, save_heatmap, save_relevancy_picture,
                   write_relevancy_pictures)
from .relevance import DEFAULT_TEMPERATURE, relevancy
from .select import (Retrieval, choose_tau, min_error_threshold, otsu_threshold, retrieve, robust_bounds,
                     subset, valley_threshold)
from .text import (CANONICAL_NEGATIVES, EmbeddingTable, TextEncoder, UnknownTextError, embed_negatives,
                   embed_queries, pca_of, project)

__all__ = ["CANONICAL_NEGATIVES", "DEFAULT_TEMPERATURE", "EmbeddingTable", "Retrieval", "TextEncoder",
           "SelectionCheck", "UnknownTextError", "check_selection", "choose_tau",
           "embed_negatives", "embed_queries", "min_error_threshold", "otsu_threshold", "pca_of", "project", "relevancy",
           "relevancy_maps", "render_language", "retrieve", "robust_bounds",
           "save_heatmap", "save_relevancy_picture", "subset", "valley_threshold", "write_relevancy_pictures"]
