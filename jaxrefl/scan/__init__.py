"""Data in: the scan bundle format (`io`), its checks before fitting, ingest of photographs,
range-data preprocessing."""
