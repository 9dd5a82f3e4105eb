"""Evaluation: video metrics and video files."""
