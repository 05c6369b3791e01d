"""Replays, metrics and plots of the localization experiments."""
