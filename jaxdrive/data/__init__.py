"""The synthetic driving world, the nuScenes reader, TFDS (ArrayRecord) builders and grain
pipelines, bucketed by (resolution, frames, views)."""
