/*
 * fuzz_job_json.c - libFuzzer harness of the job parser: the bytes of one
 * input are a POSTed job body, handed to mr_job_parse (server/job_json.c on
 * server/json_reader.c) exactly as the daemon's submit path does
 * (mr_daemon_submit), not NUL-terminated.
 *
 * Besides the sanitizers it checks the parser's contract (job_json.h): a
 * result of MR_OK comes with a job and anything else with none, only the
 * documented error codes, a JSON pointer that is "" or starts with '/', a
 * message on every failure, and the same answer for the same input
 * ("problems are looked for in a fixed order"); then the same input read
 * collecting every problem (mr_job_check, what the daemon does), which
 * must give the same result and the same first problem.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "job_json.h"

static void check(int ok, const char *what)
{
    if (!ok) {
        fprintf(stderr, "fuzz_job_json: contract broken: %s\n", what);
        abort();
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    /* A copy of exactly size bytes, so that ASan sees any read past them. */
    char *body = malloc(size ? size : 1);
    if (!body)
        return 0;
    if (size)
        memcpy(body, data, size);

    mr_job *job = (mr_job *)1;
    mr_job_error err;
    memset(&err, 0x5a, sizeof err);
    int rc = mr_job_parse(body, size, &job, &err);
    if (rc == MR_OK) {
        check(job != NULL, "MR_OK without a job");
    } else {
        check(job == NULL, "an error with a job");
        check(rc == MR_ERR_INVALID || rc == MR_ERR_LIMIT || rc == MR_ERR_NOMEM, "undocumented error code");
        check(memchr(err.pointer, '\0', sizeof err.pointer) != NULL, "pointer not terminated");
        check(memchr(err.message, '\0', sizeof err.message) != NULL, "message not terminated");
        check(err.pointer[0] == '\0' || err.pointer[0] == '/', "pointer neither \"\" nor /...");
        check(err.message[0] != '\0', "empty message");
    }

    /* Again, collecting every problem (mr_job_check, the daemon's path):
     * the reader then goes on after failures, through states a first-
     * problem reader never reaches; its first problem is the same. */
    mr_job *again = NULL;
    static mr_job_problems all;
    int rc2 = mr_job_check(body, size, &again, &all);
    check(rc2 == rc, "a different result for the same input");
    check((rc2 == MR_OK) == (again != NULL), "a job without MR_OK, or none with it");
    if (rc != MR_OK && rc != MR_ERR_NOMEM) {
        check(all.count >= 1, "no problem collected");
        check(!strcmp(err.pointer, all.items[0].pointer) && !strcmp(err.message, all.items[0].message),
              "a different first problem when collecting");
        for (size_t i = 0; i < all.count; i++) {
            check(all.items[i].pointer[0] == '\0' || all.items[i].pointer[0] == '/',
                  "a collected pointer neither \"\" nor /...");
            check(all.items[i].message[0] != '\0', "an empty collected message");
        }
    }
    mr_job_free(job);
    mr_job_free(again);
    free(body);
    return 0;
}
