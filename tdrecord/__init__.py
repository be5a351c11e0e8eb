"""Episode recording formats shared by the recorder and the readers: image codecs and channel schemas."""
