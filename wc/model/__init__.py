"""WorldContact network: tokenizer, hierarchical encoder, global-token decoder, head and topology projection."""
