"""Depth stage: frozen monocular depth estimators (relative disparity), their normalisation and cache."""
