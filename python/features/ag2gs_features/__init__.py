"""ag2gs-features: SAM masks at three levels and CLIP features of each masked
crop, written as the language_features/ layout ag2gs trains on
(docs/formats.md section 3), and CLIP text embeddings for a vocabulary."""

__version__ = "0.1.0"
