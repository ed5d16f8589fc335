"""shgm_slam: multi-robot global localization and map fusion with semantic histogram graph matching.

Implements Guo et al., "Semantic Histogram Based Graph Matching for Real-Time Multi-Robot Global
Localization in Large Scale Environment", RA-L 2021, as an incremental SLAM plugin on KISS-ICP.
"""

__version__ = "0.1.0"
