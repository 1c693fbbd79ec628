"""The live node graph from Python: node processes, replay, recorded metrics and live views.

``run_graph`` (orchestrator: leased ROS domain, nodes that die with it, no files left by
failures), ``regress_baseline`` (``rotortwin regress``: a baseline flown again by today's twin),
``lease_domain`` (domains).  Output paths are checked by the one guard of every command
(``twin_nodes.base.outputs``, called by the CLI).

May import: base, vehicle, logs, twin, identify, nodes, msgs_py.
"""

from twin_nodes.graph.orchestrator import (  # noqa: F401
    NODE_MODULES,
    Graph,
    GraphResult,
    bag_dir,
    default_params_for,
    load_aligned,
    node_command,
    ros_env,
    run_graph,
    run_node,
)
from twin_nodes.graph.domains import lease_domain  # noqa: F401
from twin_nodes.graph.regress import regress_bag, regress_baseline  # noqa: F401

__all__ = ["NODE_MODULES", "Graph", "GraphResult", "bag_dir", "default_params_for",
           "lease_domain", "load_aligned", "node_command", "regress_bag", "regress_baseline", "ros_env",
           "run_graph", "run_node"]
