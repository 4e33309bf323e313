"""Evaluation: metrics, the LLFF benchmark protocol, diagnostic pictures, aligning reconstructions."""
