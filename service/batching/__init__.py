"""Dynamic batching: the per-model queues and the policy that picks the next batch, the stereo
adapter, the inference thread and its CPU threads, and the runtime that owns them."""
