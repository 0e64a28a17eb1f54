"""gRPC plumbing shared by every baton service: channels, servers, status errors."""
