"""Attention fusion for exported PRML2 graphs: MatMul/Softmax attention -> ``com.microsoft.MultiHeadAttention``.

The exporter writes each attention as 4 Reshapes, 4 Transposes, 2 MatMuls, a Mul and a Softmax
(:class:`prml2_edge.training.model.MultiHeadAttention` while exporting). onnxruntime's transformer
optimiser does not fuse that pattern (it looks for BERT's, with a mask and a packed QKV projection;
``prml2 export --optimize`` reports ``Attention 0``), so this pass does: it matches the chain by
structure (operators, permutations, shapes), not by node names, and replaces it with one
MultiHeadAttention node (query, key and value after their projections; ``num_heads`` and the scale
read off the graph). Needs the ``onnx`` package; the result runs on onnxruntime's CPU provider.
"""

from __future__ import annotations

import numpy as np

MS_DOMAIN = "com.microsoft"


def _const_value(graph, name: str, producers: dict):
    """The value of tensor ``name`` when it is an initializer or a Constant node's output, else None."""
    from onnx import numpy_helper

    for init in graph.initializer:
        if init.name == name:
            return numpy_helper.to_array(init)
    node = producers.get(name)
    if node is not None and node.op_type == "Constant":
        for attr in node.attribute:
            if attr.name == "value":
                return numpy_helper.to_array(attr.t)
    return None


def _perm(node) -> list[int] | None:
    for attr in node.attribute:
        if attr.name == "perm":
            return list(attr.ints)
    return None


class _Graph:
    """Who produces and who consumes each tensor of an onnx graph, and the attention pieces found through it."""

    def __init__(self, graph):
        self.graph = graph
        self.producers = {o: n for n in graph.node for o in n.output}
        self.consumers: dict[str, list] = {}
        for n in graph.node:
            for i in n.input:
                self.consumers.setdefault(i, []).append(n)

    def prod(self, name: str, op: str):
        node = self.producers.get(name)
        return node if node is not None and node.op_type == op else None

    def only_consumer(self, name: str, op: str):
        nodes = self.consumers.get(name, [])
        return nodes[0] if len(nodes) == 1 and nodes[0].op_type == op else None

    def n_consumers(self, name: str) -> int:
        return len(self.consumers.get(name, []))

    def const(self, name: str):
        return _const_value(self.graph, name, self.producers)

    def head_split(self, name: str, perm: list[int]):
        """(source tensor, heads, head size, [Reshape, Transpose]) for Transpose(Reshape(src, [B, n, h, dh]))."""
        tr = self.prod(name, "Transpose")
        if tr is None or _perm(tr) != perm or self.n_consumers(tr.output[0]) != 1:
            return None
        rs = self.prod(tr.input[0], "Reshape")
        if rs is None or self.n_consumers(rs.output[0]) != 1:
            return None
        shape = self.const(rs.input[1])
        if shape is None or shape.ndim != 1 or len(shape) != 4 or shape[2] <= 0 or shape[3] <= 0:
            return None
        return rs.input[0], int(shape[2]), int(shape[3]), [rs, tr]


def fuse_attention(proto) -> int:
    """Replace every matching attention chain of ``proto`` (an onnx ModelProto, changed in place); returns how many."""
    from onnx import helper

    graph = proto.graph
    g = _Graph(graph)
    remove, add = [], []
    for softmax in [n for n in graph.node if n.op_type == "Softmax"]:
        match = _match_attention(g, softmax)
        if match is None:
            continue
        nodes, merge_r, mha = match
        remove += nodes
        add.append((merge_r, mha))
    if not add:
        return 0
    gone = {id(n) for n in remove}
    new_nodes = []
    replace = {id(r): mha for r, mha in add}
    for n in graph.node:
        if id(n) in replace:
            new_nodes.append(replace[id(n)])
        elif id(n) not in gone:
            new_nodes.append(n)
    del graph.node[:]
    graph.node.extend(new_nodes)
    _drop_dead_constants(graph)
    if not any(op.domain == MS_DOMAIN for op in proto.opset_import):
        proto.opset_import.append(helper.make_opsetid(MS_DOMAIN, 1))
    return len(add)


def _match_attention(g: _Graph, softmax):
    """The attention chain around ``softmax``: (its nodes, the final Reshape, the MultiHeadAttention node that
    replaces them), or None when the chain around it is not the exporter's attention."""
    from onnx import helper

    axis = next((a.i for a in softmax.attribute if a.name == "axis"), -1)
    if axis not in (-1, 3):
        return None
    mul = g.prod(softmax.input[0], "Mul")
    if mul is None or g.n_consumers(mul.output[0]) != 1:
        return None
    scores = scale = None
    for i, j in ((0, 1), (1, 0)):
        value = g.const(mul.input[j])
        if value is not None and value.size == 1 and g.prod(mul.input[i], "MatMul") is not None:
            scores, scale = g.prod(mul.input[i], "MatMul"), float(np.asarray(value).reshape(()))
    if scores is None or g.n_consumers(scores.output[0]) != 1:
        return None
    q = g.head_split(scores.input[0], [0, 2, 1, 3])
    k = g.head_split(scores.input[1], [0, 2, 3, 1])
    context = g.only_consumer(softmax.output[0], "MatMul")
    if q is None or k is None or context is None or context.input[0] != softmax.output[0]:
        return None
    v = g.head_split(context.input[1], [0, 2, 1, 3])
    merge_t = g.only_consumer(context.output[0], "Transpose")
    if v is None or merge_t is None or _perm(merge_t) != [0, 2, 1, 3]:
        return None
    merge_r = g.only_consumer(merge_t.output[0], "Reshape")
    if merge_r is None:
        return None
    heads, size = q[1], q[2]
    out_shape = g.const(merge_r.input[1])
    if (k[1], k[2]) != (heads, size) or (v[1], v[2]) != (heads, size) or out_shape is None \
            or len(out_shape) != 3 or int(out_shape[2]) != heads * size:
        return None
    nodes = [*q[3], *k[3], *v[3], scores, mul, softmax, context, merge_t, merge_r]
    mha = helper.make_node("MultiHeadAttention", [q[0], k[0], v[0]], [merge_r.output[0]], domain=MS_DOMAIN,
                           name=merge_r.name.rsplit("/", 1)[0] + "/MultiHeadAttention", num_heads=heads, scale=scale)
    return nodes, merge_r, mha


def _drop_dead_constants(graph) -> None:
    used = {i for n in graph.node for i in n.input} | {o.name for o in graph.output}
    keep = [n for n in graph.node if n.op_type != "Constant" or any(o in used for o in n.output)]
    del graph.node[:]
    graph.node.extend(keep)
