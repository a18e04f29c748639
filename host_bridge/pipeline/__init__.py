"""Runs -> taps -> decode -> convert -> sink (``dispatch``), the heavy topics' second process
(``offload``) and what a lagging viewer is spared (``thinning``)."""
