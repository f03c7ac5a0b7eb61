"""Evaluation stage: image metrics, the SRN protocol, mesh extraction and 3D metrics, reconstruction."""
