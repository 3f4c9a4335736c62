"""Double DQN with prior knowledge: config schemas, learner, stages, loop (checkpoints: :mod:`memrl.checkpoint`)."""
