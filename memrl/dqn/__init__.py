"""Double DQN with prior knowledge: config schemas, learner, buffers, loop, checkpoints."""
