"""Dataparsers registered by the plugin."""
