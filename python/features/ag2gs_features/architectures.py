"""Names checked before torch is imported."""

SAM_MODELS = ("vit_b", "vit_l", "vit_h")  # segment_anything's registry, without its 'default' alias
