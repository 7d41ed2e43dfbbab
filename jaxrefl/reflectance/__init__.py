"""Reflectance models: BRDFs, measurability classes, the shared reflectance prior, fills."""
