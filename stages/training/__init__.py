"""Training plumbing the training stages share: precision, checkpoints, replicas, Lightning logs, loader workers and where the starting weights come from."""
