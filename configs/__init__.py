"""Shipped YAML stage graphs (package data)."""
