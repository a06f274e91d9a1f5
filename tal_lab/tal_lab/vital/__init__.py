"""ViTAL's lab side: terrain samples and datasets, CNN training and evaluation, decode tuning, the
in-process ViTAL loop and its experiments."""
