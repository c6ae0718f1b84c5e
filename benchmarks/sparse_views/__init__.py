"""The sparse-view benchmark: its scene list (scenes.yaml) and the script that fetches the evaluation scenes."""
