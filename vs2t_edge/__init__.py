"""vs2t-edge: a fabric-sorting cell that recognises fabrics by touch.

The rooms of the architecture import under this one namespace:
``vs2t_edge.runtime`` (the cell, no torch), ``vs2t_edge.firmware_bridge`` (the gate),
``vs2t_edge.sim`` (the simulated world), ``vs2t_edge.train`` and ``vs2t_edge.export``
(offline, torch). See docs/ARCHITECTURE.md.
"""

__version__ = "0.1.0"
