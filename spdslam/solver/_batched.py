def solve_batched(*a, **k): raise NotImplementedError
class BatchedResult: pass
