"""Local-feature extractors and matchers, one module per method (XFeat + LighterGlue, ALIKED/DISK/SuperPoint +
LightGlue, SuperGlue, SIFT, SelaVPR's local features). They are built by name through
:mod:`aeroloc.matching.registry`; ``base.py`` holds the Extractor/Matcher contract.
"""
