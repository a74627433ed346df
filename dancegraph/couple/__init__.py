"""Couple dances: the lead and the follow together, from takes danced together.

``graph``: the couple graph (a node is the same bar of both partners on one shared beat grid,
with their relative placement; built beside the solo graph as ``<dataset>.couple``);
``placement``: the follow's position and facing in the lead's frame; ``render``: a path of
couple nodes as two dancers on one clock and in one world frame. The search is the solo
search (``graph.search``) run on the couple graph's arrays. Method and numbers:
docs/couples.md.
"""
