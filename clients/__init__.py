"""Thin clients that drive environments through the service."""
