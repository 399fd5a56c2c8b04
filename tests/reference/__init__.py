"""Reference implementations the tests hold the production code against: plain, obviously correct,
slow (numpy's textbook algebra, numerical derivatives).  Not part of the package."""
