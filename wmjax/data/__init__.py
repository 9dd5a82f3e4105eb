"""Data layer: Open-X RLDS specs, episode readers (tf.data / ArrayRecord), grain windows, synthetic
datasets. Depends on nothing of the model."""
