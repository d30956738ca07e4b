"""Sub-pixel laser-stripe centre extraction (Steger, centre of gravity) and its node.
"""
