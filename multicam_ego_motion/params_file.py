"""The values a ROS 2 params file (config/params.yaml) gives the nodes, for the ROS-free
runs (sequential baseline, ablation) that must run what the graph runs."""
import yaml


def node_params(params_file, node_name, names):
    """The values a params file gives node `node_name` (any namespace), among `names`."""
    with open(params_file) as f:
        doc = yaml.safe_load(f) or {}
    out = {}
    for section, body in doc.items():
        if section.endswith(node_name):
            out.update({k: v for k, v in (body or {}).get('ros__parameters', {}).items() if k in names})
    return out


def quarter_params_from(params_file):
    from camera_pose_nodes.quarter_estimator import QuarterParams
    return node_params(params_file, 'quarter_node', set(QuarterParams.__dataclass_fields__))


def fusion_params_from(params_file):
    """The general arbiter's fusion parameters, so that the sequential baseline runs what the
    graph runs."""
    from arbiter_node.general_fusion import PARAMETERS
    return node_params(params_file, 'general_arbiter', set(PARAMETERS))


def camera_fusion_params_from(params_file):
    """The camera arbiters' quarter-fusion parameters (outlier gate, correlation): a
    sequential baseline with the code's defaults instead rejected a quarter the graph kept."""
    from arbiter_node.quarter_fusion import PARAMETERS
    return node_params(params_file, 'camera_arbiter', set(PARAMETERS))


def sync_window_from(params_file) -> float:
    """The general arbiter's frame window (sync_window_s; 0 when the file does not set it):
    a lockstep player and the sequential baseline group frames by it as the arbiter does."""
    return float(node_params(params_file, 'general_arbiter', {'sync_window_s'}).get('sync_window_s', 0.0))


def with_node_param(params_file, node_name, name, value, out_file):
    """A copy of the params file, written to out_file, that gives node `node_name` (every
    section for it, whatever its namespace; a `/**/node_name` one if there is none) `name`:
    `value`. The rest of the file as it was."""
    with open(params_file) as f:
        doc = yaml.safe_load(f) or {}
    sections = [s for s in doc if s.endswith(node_name)] or [f'/**/{node_name}']
    for s in sections:
        doc[s] = doc.get(s) or {}
        doc[s].setdefault('ros__parameters', {})[name] = value
    with open(out_file, 'w') as f:
        yaml.safe_dump(doc, f, sort_keys=False)
    return out_file
