"""The domain: the type system, the MongoDB store, the embedded mongod and the settings."""
