"""Shared environment and data-collection code for CLAW."""
