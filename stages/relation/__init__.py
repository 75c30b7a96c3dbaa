"""The `relation` stage: the DeepWORD graph network (GAT-re-weighted prior edges, GCN, cosine scores)."""
