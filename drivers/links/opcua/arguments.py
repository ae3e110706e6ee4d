"""Call arguments checked against a method's ``InputArguments`` before the method runs.

asyncua hands a method whatever the client sent: a String where the model says UInt16 reached the
station as a trigger and was stored, and a missing argument raised inside the method
(BadUnexpectedError, with a traceback in the log). OPC 10000-4 §5.11.2 (Call) has the answers:
too few arguments ``BadArgumentsMissing``, too many ``BadTooManyArguments``, one of the wrong
type ``BadInvalidArgument`` with ``BadTypeMismatch`` for that argument in
``InputArgumentResults``; the method is not run, nothing is measured or stored. The types are
the model's own (``Argument.DataType``, ``ValueRank``), read from the address space; a Null
value stands for an argument left empty (the methods take it as their default).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

from asyncua import Node, Server, ua

from .events import TypeHierarchy

_UA: Any = ua  # asyncua's stubs type a status code's value as UInt32
_ANY = {24}  # BaseDataType: a Variant of any type
_NUMBERS = {26: set(range(2, 12)), 27: {2, 4, 6, 8}, 28: {3, 5, 7, 9}}  # Number, (U)Integer
_STRUCTURE, _ENUMERATION = 22, 29


def _status(code: int) -> ua.StatusCode:
    return _UA.StatusCode(code)


def builtin(datatype: ua.NodeId, types: TypeHierarchy) -> int:
    """The built-in type (a VariantType number, or an abstract Number type) values of
    ``datatype`` are encoded as: the nearest of its supertypes in namespace 0 that is one."""
    for t in types.chain(datatype):
        if t.NamespaceIndex == 0 and isinstance(t.Identifier, int):
            if t.Identifier == _ENUMERATION:
                return int(ua.VariantType.Int32)
            if 1 <= t.Identifier <= 25 or t.Identifier in _NUMBERS:
                return t.Identifier
    return 24


def fits(arg: ua.Argument, value: ua.Variant, types: TypeHierarchy) -> bool:
    """Whether ``value`` is of the argument's DataType and ValueRank."""
    if value.VariantType == ua.VariantType.Null:
        return True
    rank = arg.ValueRank
    is_array = bool(value.is_array)
    if (rank == -1 and is_array) or (rank >= 0 and not is_array):
        return False
    kind = builtin(arg.DataType, types)
    vt = int(value.VariantType)
    if kind in _ANY:
        return True
    if kind in _NUMBERS:
        return vt in _NUMBERS[kind]
    if vt != kind:
        return False
    if kind == _STRUCTURE:
        items = value.Value if is_array else [value.Value]
        return all(arg.DataType in types.supertypes(getattr(type(x), "data_type", ua.NodeId()))
                   for x in items or [])
    return True


def checked(call: Callable[..., Any], arguments: list[ua.Argument],
            types: TypeHierarchy) -> Callable[..., Any]:
    """``call`` (a method's callback) run only with the arguments its model asks for."""

    async def check(parent: ua.NodeId, *args: ua.Variant) -> Any:
        refused = ua.CallMethodResult()
        if len(args) < len(arguments):
            refused.StatusCode = _status(ua.StatusCodes.BadArgumentsMissing)
            return refused
        if len(args) > len(arguments):
            refused.StatusCode = _status(ua.StatusCodes.BadTooManyArguments)
            return refused
        results = [_status(ua.StatusCodes.Good if fits(a, value, types)
                                 else ua.StatusCodes.BadTypeMismatch)
                   for a, value in zip(arguments, args, strict=True)]
        if not all(r.is_good() for r in results):
            refused.StatusCode = _status(ua.StatusCodes.BadInvalidArgument)
            refused.InputArgumentResults = results
            return refused
        out = call(parent, *args)
        return await out if inspect.isawaitable(out) else out

    return check


async def check_arguments(server: Server, root: Node) -> int:
    """Put :func:`checked` before every linked method under ``root``; how many."""
    space = server.iserver.aspace
    types = TypeHierarchy(space)
    done = 0
    todo = [root]
    while todo:
        node = todo.pop()
        for child in await node.get_children(refs=ua.ObjectIds.HierarchicalReferences):
            cls = await child.read_node_class()
            if cls == ua.NodeClass.Object:
                todo.append(child)
            elif cls == ua.NodeClass.Method and (call := space[child.nodeid].call) is not None:
                arguments: list[ua.Argument] = []
                for prop in await child.get_properties():
                    if (await prop.read_browse_name()).Name == "InputArguments":
                        arguments = list(await prop.read_value() or [])
                server.link_method(child, checked(call, arguments, types))
                done += 1
    return done
