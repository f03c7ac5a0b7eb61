"""Data stage: camera conventions, the SRN-format reader and the synthetic SRN-protocol generator."""
