"""Offline RL shared by every method."""
