"""Shared plumbing every stage uses: user-facing errors, atomic file writes, stage reports."""
