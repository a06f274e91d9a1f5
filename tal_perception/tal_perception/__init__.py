"""Heightmaps, foothold evaluation criteria, VFA and VPA with their CNN approximations; nodes vfa and vpa."""
