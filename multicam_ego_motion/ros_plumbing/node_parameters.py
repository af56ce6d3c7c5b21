"""Declare a node's ROS parameters from a ROS-free table: name -> (default, description, min, max).

The cores own their parameters (defaults, meaning, valid range); nodes declare them with
descriptors so that `ros2 param describe` shows them and a params file value out of range is
rejected at start with the allowed range in the message.
"""
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from multicam_ego_motion.errors import UserError


def declare_from_table(node, table: dict) -> dict:
    """Declare every parameter of `table`; return {name: value} after overrides, range-checked."""
    values = {}
    for name, (default, description, lo, hi) in table.items():
        desc = ParameterDescriptor(description=description)
        if isinstance(default, bool) or lo is None:
            pass
        elif isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        elif isinstance(default, float):
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        try:
            value = node.declare_parameter(name, default, desc).value
        except Exception as e:  # rclpy raises InvalidParameterValueException with its own text
            raise UserError(f'{node.get_fully_qualified_name()}: parameter {name}: {e} '
                            f'(allowed range [{lo}, {hi}])') from None
        if lo is not None and not isinstance(default, bool) and not (lo <= value <= hi):
            raise UserError(f'{node.get_fully_qualified_name()}: parameter {name} = {value} is out of range '
                            f'[{lo}, {hi}] ({description})')
        values[name] = value
    return values
